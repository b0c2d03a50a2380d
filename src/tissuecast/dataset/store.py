"""The data-set store: one Zarr v3 directory per data set, readable with zarr alone.

Schema (``schema = "tissuecast.dataset"``, ``schema_version = 1``); N samples, n_v mesh
vertices, n_b LBO basis vectors; vertex ids 0-based; units mm, N, MPa::

    STORE/                          root group; attributes:
        schema, schema_version      "tissuecast.dataset", 1
        created                     ISO-8601 UTC time the store was created
        versions                    {package: version} of the software that made it
        config_toml                 the full configuration (TOML text)
        mesh_fingerprint            TetMesh.fingerprint() of the mesh
        n_samples, n_lbo, n_test2   N = n_lbo + n_test2; LBO samples come first
        split_labels                {"0": "train", "1": "valid", "2": "test1", "3": "test2"}
        status_labels               {"0": "pending", "1": "done", "2": "failed"}
        calibration                 force-magnitude calibration (see calibrate.py), null until done
        failures                    {"<sample index>": "reason"} of failed samples
        scenario                    the clinical scenario (Scenario.summary(): supports, springs,
                                    gravity, indentation, material draws); absent in stores made
                                    before scenarios existed (they are the paper's: pins + LBO)
      mesh/points     (n_v, 3) float64 mm        mesh/tets (m, 4) int64 (0-based, positive volume)
      markers         (n_d,)  int64 fiducial-marker vertex ids (pick order)
      fixed           (k,)    int64 vertex ids fixed in all components: the pins and the attached
                              region of the scenario (the paper's set-up: the pins)
      lbo/vertices    (s,)    int64 surface vertex ids     lbo/vectors (s, n_b) float64 1/mm
      lbo/eigenvalues (n_b,)  float64 1/mm^2               lbo/mass    (s,)     float64 mm^2
      samples/displacements (N, n_v, 3) float32 mm; one chunk per sample; NaN unless done
      samples/forces        (N, n_v, 3) float32 N, dense (zero off the surface; compresses
                            well); one chunk per sample; written for done and failed samples
      samples/weights       (N, n_b, 3) float64 LBO weights W (test-2: of the blended LBO field)
      samples/alpha         (N,) float64 N, force magnitude  (NaN until solved)
      samples/beta          (N,) float64 LBO share of test-2 samples; NaN for LBO samples
      samples/seed          (N,) uint64 per-sample seed (numpy default_rng(seed) makes the field)
      samples/split         (N,) int8 split code (split_labels)
      samples/status        (N,) int8 0 pending, 1 done, 2 failed (codes.SampleStatus)
      samples/increments, iterations, factorizations   (N,) int32 solver counts (all attempts)
      samples/attempts      (N,) int8 solver attempts (1 + retries used)
      samples/load_fraction (N,) float64 share of the load reached (1 when done)
      samples/max_displacement (N,) float32 mm, largest vertex displacement (NaN unless done)
      samples/seconds       (N,) float64 wall-clock solve time (the only non-reproducible array)
      samples/predicted     (N,) int8 initial guess (codes.InitialGuess): 0 zero (no reduced
                            model yet), 1 the reduced model's prediction, 2 the guess did not
                            work (then zero), 3 a calibration pilot's solution of the previous round
      scenario/pinned, scenario/attached, scenario/spring_region   (k,) int64 vertex ids of the
                            pins, the attached region and the elastic support's region
      scenario/spring_nodes (s,) int64 element nodes with a spring (P2: vertices, then mid-edge
                            nodes as in reduced/snapshots); scenario/spring_stiffness (s, 3, 3)
                            float64 N/mm, each node's spring K_a (present with an elastic support)
      scenario/youngs_modulus (m,) float64 MPa, scenario/poisson_ratio (m,) float64,
      scenario/material_region (m,) int64 (-1 = [material])   per element (with material regions)
      samples/gravity_direction   (N, 3) float64 unit direction of gravity during surgery drawn
                            for the sample (NaN: not drawn yet, or no gravity change)
      samples/indent_centre (N,) int64 vertex id of the indentation patch's centre (-1: none)
      samples/indent_depth, samples/indent_slide (N,) float64 mm, the indentation's depth along
                            the inward normal and its slide along the surface (NaN: none)
      samples/indent_displacement (N, 3) float64 mm, the displacement given to every patch vertex
      (the scenario/ group and the samples' draw arrays exist in stores whose scenario has them;
      a sample's draws are a function of its seed: scenario.scenario_rng; the patch vertices
      follow from the centre, the mesh and the config)
      samples/batch         (N,) int32 the batch each sample of the sample phase is solved in
                            (dataset.batch_size > 1 with a reduced model; -1: solved alone);
                            absent until that phase first starts; the root attribute
                            ``batches`` ({size, count}) is written after it and marks it complete
      reduced/samples       (s,) int64 ids of the samples whose full solutions built the reduced
                            model (dataset.predictor = "reduced"; absent otherwise)
      reduced/snapshots     (s, n_nodes, 3) float64 mm their displacements at every element node
                            (vertices first, then P2 mid-edge nodes in TetMesh.edges order);
                            NaN until solved; one chunk per sample
      reduced/basis         (n_free, r) float64 the reduced basis over the free dofs (node-major
                            x, y, z; nodes of fixed vertices left out)
      reduced/elements (k,) int64, reduced/weights (k,) float64   ECSW elements (0-based) and
                            weights; the root attribute ``reduced`` ({modes, elements, fit_error,
                            snapshots}) is written last and marks the model complete

Chunks are compressed with Blosc/zstd. Only the parent process writes; every chunk write is
atomic (zarr's LocalStore writes a temporary file and renames it). A sample's field chunks
are written when it is solved; its 1-D values, weights and failure reason at the next
:meth:`StoreWriter.flush`, which writes ``status`` last. So an interrupted run (``kill -9``,
full disk) leaves a readable store whose pending samples are solved again on the next run. A new store is built
in ``STORE.partial`` and renamed into place once its skeleton is complete.
"""

from __future__ import annotations

import json
import os
import shutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..errors import DatasetError, require
from .codes import STATUS_NAMES, InitialGuess, SampleStatus
from .plan import SPLIT_NAMES, SamplePlan
from .worker import SampleResult

__all__ = ["SCHEMA", "SCHEMA_VERSION", "STATUS_NAMES", "StoreWriter", "package_versions", "check_schema",
           "read_lbo_basis"]

SCHEMA = "tissuecast.dataset"
SCHEMA_VERSION = 1
_BLOCK = 256  # chunk length of the per-sample 1-D arrays and weights

# per-sample scalar arrays: name -> (dtype, fill value)
SCALARS = {
    "alpha": ("float64", np.nan),
    "beta": ("float64", np.nan),
    "seed": ("uint64", 0),
    "split": ("int8", -1),
    "status": ("int8", SampleStatus.PENDING.value),
    "increments": ("int32", 0),
    "iterations": ("int32", 0),
    "factorizations": ("int32", 0),
    "attempts": ("int8", 0),
    "load_fraction": ("float64", np.nan),
    "max_displacement": ("float32", np.nan),
    "seconds": ("float64", np.nan),
    "predicted": ("int8", InitialGuess.ZERO.value),
}
_ADDED_LATER = ("predicted",)  # per-sample arrays that stores of earlier releases lack (created on open)
#: Per-sample scenario draws: name -> (trailing shape, dtype, fill value), in stores whose
#: scenario draws a gravity direction or an indentation.
DRAWS = {
    "gravity_direction": ((3,), "float64", np.nan),
    "indent_centre": ((), "int64", -1),
    "indent_depth": ((), "float64", np.nan),
    "indent_slide": ((), "float64", np.nan),
    "indent_displacement": ((3,), "float64", np.nan),
}


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape a data set's numbers."""
    import platform
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in ("tissuecast", "numpy", "scipy", "numba", "zarr", "scikit-sparse", "robust-laplacian", "meshio"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def _zarr():
    return require("zarr", "data", "data-set stores")


def _compressor():
    return _zarr().codecs.BloscCodec(cname="zstd", clevel=5, shuffle="shuffle")


def check_schema(root, path) -> None:
    """Raise DatasetError unless ``root`` is a tissuecast data set of a known schema."""
    attrs = root.attrs
    if attrs.get("schema") != SCHEMA:
        raise DatasetError(f"{str(path)!r} is not a tissuecast data set (no schema = {SCHEMA!r} attribute); "
                           "create one with `tissuecast simulate CONFIG --store PATH`")
    version = attrs.get("schema_version")
    if not isinstance(version, int) or version > SCHEMA_VERSION or version < 1:
        raise DatasetError(f"data set {str(path)!r} has schema version {version!r}, but this tissuecast reads "
                           f"versions 1..{SCHEMA_VERSION}; upgrade tissuecast to read it")


def read_lbo_basis(root):
    """The stored :class:`~tissuecast.forces.LBOBasis` of a store's root group (read-only arrays)."""
    from ..forces import LBOBasis

    arrays = [np.asarray(root[f"lbo/{k}"][...]) for k in ("vertices", "vectors", "eigenvalues", "mass")]
    for a in arrays:
        a.setflags(write=False)
    return LBOBasis(*arrays)


def read_scenario_arrays(root) -> dict[str, np.ndarray] | None:
    """The resolved scenario's stored arrays (``scenario/*``: pins, attached region, springs,
    indentation access; :func:`tissuecast.scenario.restore_scenario` rebuilds the scenario
    from them) of a store's root group, or None for a store without them (the paper's set-up)."""
    if "scenario" not in root:
        return None
    group = root["scenario"]
    return {name: np.asarray(group[name][...]) for name in group.array_keys()}


class StoreWriter:
    """Writes samples into a store (the parent process is the only writer).

    Attributes:
        path: the store directory.  root: its zarr group.
        status: (N,) int8 in-memory copy of ``samples/status``.
    """

    def __init__(self, path: Path, root):
        self.path, self.root = path, root
        self.samples = root["samples"]
        for name in _ADDED_LATER:
            if name not in self.samples:
                dtype, fill = SCALARS[name]
                n = self.samples["status"].shape[0]
                self.samples.create_array(name, shape=(n,), dtype=dtype, chunks=(min(_BLOCK, n),), fill_value=fill,
                                          compressors=_compressor(), dimension_names=("sample",))
        self._draws = tuple(name for name in DRAWS if name in self.samples)
        self._arrays = {name: self.samples[name] for name in (*SCALARS, "displacements", "forces", "weights",
                                                              *self._draws)}
        self._mem = {name: np.array(self._arrays[name][...]) for name in (*SCALARS, "weights", *self._draws)}
        self.status = self._mem["status"]
        self._failures = dict(root.attrs.get("failures") or {})
        self._dirty: set[int] = set()  # blocks of the 1-D arrays changed since the last flush
        self._snapshot_rows: np.ndarray | None = None  # reduced/samples, once read or created

    # ------------------------------------------------------------ creation / opening
    @classmethod
    def create(cls, path, *, config_toml: str, mesh, markers, fixed, basis, plan: SamplePlan,
               scenario=None) -> "StoreWriter":
        """Create a new store at ``path`` (which must not exist) and return its writer.

        ``scenario``: the resolved :class:`~tissuecast.scenario.Scenario` (its summary, arrays
        and, if it draws per sample, the draw arrays are stored), or None."""
        zarr = _zarr()
        path = Path(path)
        tmp = path.with_name(path.name + ".partial")
        if tmp.exists():
            _remove_partial(tmp)
        root = zarr.create_group(zarr.storage.LocalStore(tmp), zarr_format=3, attributes={
            "schema": SCHEMA, "schema_version": SCHEMA_VERSION,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": package_versions(), "config_toml": config_toml,
            "mesh_fingerprint": mesh.fingerprint(),
            "n_samples": plan.n_samples, "n_lbo": plan.n_lbo, "n_test2": plan.n_samples - plan.n_lbo,
            "split_labels": {str(k): v for k, v in SPLIT_NAMES.items()},
            "status_labels": {str(k): v for k, v in STATUS_NAMES.items()},
            "units": {"length": "mm", "force": "N", "stress": "MPa"},
            "calibration": None, "failures": {},
            **({} if scenario is None else {"scenario": json.loads(json.dumps(scenario.summary(), default=float))}),
        })  # attributes go into the very first zarr.json: a .partial dir is always recognisable
        comp = _compressor()

        def put(name, data):
            data = np.ascontiguousarray(data)
            chunks = tuple(max(1, d) for d in data.shape) or None  # an empty array still needs a chunk
            a = root.create_array(name, shape=data.shape, dtype=data.dtype, chunks=chunks, compressors=comp)
            a[...] = data

        put("mesh/points", np.asarray(mesh.points, dtype=np.float64))
        put("mesh/tets", np.asarray(mesh.tets, dtype=np.int64))
        put("markers", np.asarray(markers, dtype=np.int64))
        put("fixed", np.asarray(fixed, dtype=np.int64))
        put("lbo/vertices", np.asarray(basis.vertices, dtype=np.int64))
        put("lbo/vectors", np.asarray(basis.vectors, dtype=np.float64))
        put("lbo/eigenvalues", np.asarray(basis.eigenvalues, dtype=np.float64))
        put("lbo/mass", np.asarray(basis.mass, dtype=np.float64))
        n, nv, nb = plan.n_samples, mesh.n_vertices, basis.vectors.shape[1]
        s = root.create_group("samples")
        s.create_array("displacements", shape=(n, nv, 3), dtype="float32", chunks=(1, nv, 3),
                       fill_value=np.nan, compressors=comp, dimension_names=("sample", "vertex", "axis"))
        s.create_array("forces", shape=(n, nv, 3), dtype="float32", chunks=(1, nv, 3), fill_value=0.0,
                       compressors=comp, dimension_names=("sample", "vertex", "axis"))
        s.create_array("weights", shape=(n, nb, 3), dtype="float64", chunks=(_BLOCK, nb, 3), fill_value=np.nan,
                       compressors=comp, dimension_names=("sample", "basis", "axis"))
        for name, (dtype, fill) in SCALARS.items():
            s.create_array(name, shape=(n,), dtype=dtype, chunks=(min(_BLOCK, n),), fill_value=fill,
                           compressors=comp, dimension_names=("sample",))
        if scenario is not None:
            for name, data in scenario.arrays().items():
                put(f"scenario/{name}", data)
            if scenario.draws_per_sample:
                for name, (shape, dtype, fill) in DRAWS.items():
                    s.create_array(name, shape=(n, *shape), dtype=dtype, chunks=(min(_BLOCK, n), *shape),
                                   fill_value=fill, compressors=comp,
                                   dimension_names=("sample",) + (("axis",) if shape else ()))
        s["beta"][:] = plan.beta
        s["seed"][:] = plan.seed
        s["split"][:] = plan.split
        os.rename(tmp, path)  # the store appears complete or not at all
        return cls.open(path)

    @classmethod
    def open(cls, path) -> "StoreWriter":
        """Open an existing store for appending (schema checked; removes stale temp files)."""
        zarr = _zarr()
        path = Path(path)
        root = _open_root(path, mode="r+")
        check_schema(root, path)
        for stale in path.rglob("*.partial"):  # leftovers of a write interrupted by kill -9
            stale.unlink(missing_ok=True)
        return cls(path, zarr.open_group(zarr.storage.LocalStore(path), mode="r+"))

    # ------------------------------------------------------------ state
    @property
    def config_toml(self) -> str:
        return self.root.attrs["config_toml"]

    @property
    def calibration(self) -> dict | None:
        return self.root.attrs.get("calibration")

    def set_calibration(self, calibration: dict) -> None:
        """Record the force-magnitude calibration (JSON-able dict with an ``alpha`` key)."""
        self.root.attrs["calibration"] = json.loads(json.dumps(calibration))

    def read(self, name: str) -> np.ndarray:
        """A whole stored array as numpy (e.g. ``"mesh/points"``)."""
        return np.asarray(self.root[name][...])

    # ------------------------------------------------------------ reduced model
    @property
    def reduced(self) -> dict | None:
        """The reduced model's record (None until it is complete)."""
        return self.root.attrs.get("reduced")

    def snapshot_rows(self, samples: np.ndarray, n_nodes: int) -> np.ndarray:
        """The ``reduced/samples`` ids (created as ``samples`` on first use); (s,) int64."""
        if self._snapshot_rows is not None:
            return self._snapshot_rows
        if "reduced/samples" not in self.root:
            comp = _compressor()
            samples = np.asarray(samples, dtype=np.int64)
            self.root.create_array("reduced/snapshots", shape=(len(samples), n_nodes, 3), dtype="float64",
                                   chunks=(1, n_nodes, 3), fill_value=np.nan, compressors=comp,
                                   dimension_names=("snapshot", "node", "axis"))
            a = self.root.create_array("reduced/samples", shape=samples.shape, dtype="int64",
                                       chunks=samples.shape, compressors=comp)
            a[...] = samples  # written last: its presence means the snapshot array exists
        self._snapshot_rows = self.read("reduced/samples")
        return self._snapshot_rows

    def snapshot_done(self) -> np.ndarray:
        """(s,) bool, True where ``reduced/snapshots`` holds a solution."""
        a = self.root["reduced/snapshots"]
        return np.array([bool(np.isfinite(a[i, 0, 0])) for i in range(a.shape[0])])

    def write_snapshot(self, row: int, nodal: np.ndarray) -> None:
        """Store one basis sample's displacements at every element node (one atomic chunk write)."""
        self.root["reduced/snapshots"][row] = np.asarray(nodal, dtype=np.float64)

    def set_reduced(self, basis: np.ndarray, elements: np.ndarray, weights: np.ndarray, record: dict) -> None:
        """Store the reduced model; the ``reduced`` attribute last."""
        comp = _compressor()
        for name, data in (("basis", basis), ("elements", elements), ("weights", weights)):
            data = np.ascontiguousarray(data)
            key = f"reduced/{name}"
            if key in self.root:
                del self.root[key]
            a = self.root.create_array(key, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=comp)
            a[...] = data
        self.root.attrs["reduced"] = json.loads(json.dumps(record))

    # ------------------------------------------------------------ batches
    @property
    def batches(self) -> dict | None:
        """The batch plan's record ``{size, count}`` (None until it is set)."""
        return self.root.attrs.get("batches")

    def set_batches(self, batch_of: np.ndarray, size: int) -> None:
        """Store the batch of every sample ((N,) int32, -1 = none); the ``batches`` attribute last."""
        batch_of = np.ascontiguousarray(batch_of, dtype=np.int32)
        if "samples/batch" in self.root:
            del self.root["samples/batch"]
        n = len(batch_of)
        a = self.root.create_array("samples/batch", shape=(n,), dtype="int32", chunks=(n,), fill_value=-1,
                                   compressors=_compressor(), dimension_names=("sample",))
        a[...] = batch_of
        self.root.attrs["batches"] = {"size": int(size), "count": int(batch_of.max(initial=-1)) + 1}

    def pending(self) -> np.ndarray:
        """Indices of samples not solved yet, ascending."""
        return np.flatnonzero(self.status == SampleStatus.PENDING)

    # ------------------------------------------------------------ writing
    def write_sample(self, r: SampleResult) -> None:
        """Write one sample's field chunks now; its per-sample values and status at :meth:`flush`.

        The status of a sample reaches the disk only after all its data (flush writes the
        1-D arrays, then the failure reasons, then ``status`` last), so an interruption at
        any point leaves samples either complete or pending.
        """
        i, a = r.index, self._arrays
        if r.displacement is not None:
            a["displacements"][i] = r.displacement
        a["forces"][i] = r.forces
        m = self._mem
        m["weights"][i] = r.weights
        if self._draws and r.draw is not None:
            for name, value in _draw_values(r.draw).items():
                m[name][i] = value
        values = {"alpha": r.alpha, "increments": r.increments, "iterations": r.iterations,
                  "factorizations": r.factorizations, "attempts": r.attempts, "load_fraction": r.load_fraction,
                  "max_displacement": r.max_displacement if r.status == SampleStatus.DONE else np.nan, "seconds": r.seconds,
                  "predicted": r.predicted}
        for name, v in values.items():
            m[name][i] = v
        if r.status == SampleStatus.FAILED:
            self._failures[str(i)] = r.reason
        self.status[i] = r.status
        self._dirty.add(i // _BLOCK)

    def flush(self) -> None:
        """Write the per-sample values of the samples written since the last flush, status last."""
        if not self._dirty:
            return
        blocks = sorted(self._dirty)
        n = len(self.status)
        names = [k for k in (*SCALARS, "weights", *self._draws) if k not in ("status", "beta", "seed", "split")]
        for name in names + ["failures", "status"]:
            if name == "failures":
                stored = self.root.attrs.get("failures") or {}
                if len(stored) != len(self._failures):
                    self.root.attrs["failures"] = {k: self._failures[k] for k in sorted(self._failures, key=int)}
                continue
            for blk in blocks:  # whole chunks from memory: one write each, no read
                lo, hi = blk * _BLOCK, min((blk + 1) * _BLOCK, n)
                self._arrays[name][lo:hi] = self._mem[name][lo:hi]
        self._dirty.clear()

def _draw_values(draw) -> dict:
    """A :class:`~tissuecast.scenario.ScenarioDraw` as the values of the :data:`DRAWS` arrays."""
    out = {}
    if draw.gravity_direction is not None:
        out["gravity_direction"] = draw.gravity_direction
    ind = draw.indentation
    if ind is not None:
        out.update(indent_centre=ind.centre, indent_depth=ind.depth, indent_slide=ind.slide,
                   indent_displacement=ind.displacement)
    return out


def open_root(path: Path):
    """The store's root Zarr group, read-only, its schema checked.

    Raises:
        DatasetError: as :func:`~.reader.open_dataset`.
    """
    root = _open_root(Path(path), mode="r")
    check_schema(root, Path(path))
    return root


def _open_root(path: Path, mode: str):
    zarr = _zarr()
    if not path.exists():
        raise DatasetError(f"data set {str(path)!r} does not exist; create it with `tissuecast simulate CONFIG --store {path}`")
    if not (path / "zarr.json").is_file():
        raise DatasetError(f"{str(path)!r} is not a Zarr v3 store (no zarr.json); is it a tissuecast data set?")
    try:
        return zarr.open_group(zarr.storage.LocalStore(path, read_only=(mode == "r")), mode=mode)
    except (ValueError, KeyError, OSError, TypeError) as exc:
        raise DatasetError(f"cannot open data set {str(path)!r}: {exc}") from exc


def _remove_partial(tmp: Path) -> None:
    """Remove an interrupted store creation, but only if it is ours."""
    meta = tmp / "zarr.json"
    try:
        if meta.is_file():
            ours = json.loads(meta.read_text()).get("attributes", {}).get("schema") == SCHEMA
        else:
            ours = not any(tmp.iterdir())
    except (OSError, ValueError):
        ours = False
    if not ours:
        raise DatasetError(f"{str(tmp)!r} exists and is not an interrupted tissuecast store; move it away and retry")
    shutil.rmtree(tmp)
