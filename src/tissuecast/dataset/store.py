"""Writing a data-set store (its layout: :mod:`.schema`, ``docs/dataset-schema.md``).

:meth:`StoreWriter.create` makes a new store from a configuration and its resolved scenario;
:meth:`StoreWriter.resume` opens an existing one to continue it, after checking that the
configuration, mesh, markers and supports are those it was made with (a store is never
overwritten, and its samples stay one data set).

Chunks are compressed with Blosc/zstd. Only the parent process writes; every chunk write is
atomic (zarr's LocalStore writes a temporary file and renames it). A sample's field chunks
are written when it is solved; its 1-D values, weights and failure reason at the next
:meth:`StoreWriter.flush`, which writes ``status`` last. So an interrupted run (``kill -9``,
full disk) leaves a readable store whose pending samples are solved again on the next run. A new store is built
in ``STORE.partial`` and renamed into place once its skeleton is complete.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import tomllib
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..config import Config, DatasetConfig, config_from_dict, config_to_dict, config_to_toml
from ..errors import DatasetError
from .codes import STATUS_NAMES, SampleStatus
from .sample_plan import SPLIT_NAMES, SamplePlan
from .schema import (ADDED_LATER, BLOCK, DRAWS, INSTRUMENT_PREFIX, PARAMETERS, SCALARS, SCHEMA, SCHEMA_VERSION,
                     check_schema, compressor, instrument_arrays, open_root, open_store_root, read_lbo_basis,
                     read_scenario_arrays, zarr_module)
from .worker import SampleResult

__all__ = ["SCHEMA", "SCHEMA_VERSION", "STATUS_NAMES", "StoreWriter", "package_versions", "check_schema",
           "read_lbo_basis", "read_scenario_arrays", "open_root", "data_config", "data_differences"]

log = logging.getLogger(__name__)

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


class StoreWriter:
    """Writes samples into a store (the parent process is the only writer).

    Attributes:
        path: the store directory.  root: its zarr group.
        status: (N,) int8 in-memory copy of ``samples/status``.
    """

    def __init__(self, path: Path, root):
        self.path, self.root = path, root
        self.samples = root["samples"]
        for name in ADDED_LATER:
            if name not in self.samples:
                dtype, fill = SCALARS[name]
                n = self.samples["status"].shape[0]
                self.samples.create_array(name, shape=(n,), dtype=dtype, chunks=(min(BLOCK, n),), fill_value=fill,
                                          compressors=compressor(), dimension_names=("sample",))
        self._draws = tuple(name for name in {**DRAWS, **PARAMETERS} if name in self.samples) + tuple(
            sorted(name for name in self.samples.array_keys() if name.startswith(INSTRUMENT_PREFIX)))
        self._arrays = {name: self.samples[name] for name in (*SCALARS, "displacements", "forces", "weights",
                                                              *self._draws)}
        self._mem = {name: np.array(self._arrays[name][...]) for name in (*SCALARS, "weights", *self._draws)}
        self.status = self._mem["status"]
        self._failures = dict(root.attrs.get("failures") or {})
        self._dirty: set[int] = set()  # blocks of the 1-D arrays changed since the last flush
        self._snapshot_rows: np.ndarray | None = None  # reduced/samples, once read or created

    # ------------------------------------------------------------ creation / opening
    @classmethod
    def create(cls, path, *, config: Config, markers, plan: SamplePlan, scenario) -> "StoreWriter":
        """Create a new store at ``path`` (which must not exist) and return its writer.

        Args:
            path: the store directory (built in ``PATH.partial``, renamed when complete).
            config: the data set's configuration; the store records it with the default
                ``dataset.workers`` and ``dataset.scheduler`` (where the samples are solved is
                not part of the data set: a cluster run and a local run give one store).
            markers: (n_d,) int fiducial-marker vertex ids (0-based).
            plan: the sample plan (:func:`~.sample_plan.make_plan`).
            scenario: the resolved :class:`~tissuecast.scenario.Scenario`: its mesh, supported
                vertices (``fixed``), LBO basis, summary and arrays are stored, and the draw
                arrays when it draws per sample.
        """
        zarr = zarr_module()
        path = Path(path)
        tmp = path.with_name(path.name + ".partial")
        if tmp.exists():
            _remove_partial(tmp)
        root = zarr.create_group(zarr.storage.LocalStore(tmp), zarr_format=3,
                                 attributes=_root_attributes(config, plan, scenario))
        # the attributes go into the very first zarr.json: a .partial dir is always recognisable
        _put_setup(root, markers, scenario)
        _create_sample_arrays(root, plan, scenario)
        os.rename(tmp, path)  # the store appears complete or not at all
        return cls.open(path)

    @classmethod
    def open(cls, path) -> "StoreWriter":
        """Open an existing store for appending (schema checked; removes stale temp files)."""
        zarr = zarr_module()
        path = Path(path)
        root = open_store_root(path, mode="r+")
        check_schema(root, path)
        for stale in path.rglob("*.partial"):  # leftovers of a write interrupted by kill -9
            stale.unlink(missing_ok=True)
        return cls(path, zarr.open_group(zarr.storage.LocalStore(path), mode="r+"))

    @classmethod
    def resume(cls, path, *, config: Config, markers, scenario) -> "StoreWriter":
        """Open an existing store to continue it with ``config``, its markers and resolved
        scenario, once :meth:`check_compatible` has accepted them."""
        writer = cls.open(path)
        writer.check_compatible(config, markers, scenario)
        return writer

    def check_compatible(self, config: Config, markers, scenario) -> None:
        """Check that the store can be continued with ``config``, ``markers`` ((n_d,) int) and
        the resolved ``scenario``: the same data settings (:func:`data_config`; the batch
        settings only until the store fixed its batches), the same mesh (by fingerprint) and
        the same markers and supported vertices. A store without pins keeps its own markers
        (they do not enter its simulation), and a store with springs other than the config's
        goes on with its own (both logged).

        Raises:
            DatasetError: what differs, and what to do (a store is never overwritten).
        """
        _check_config(self, config)
        _check_mesh(self, scenario.mesh)
        _check_ids(self, config, markers, scenario.supported)
        _check_springs(self, scenario)

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
            comp = compressor()
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
        comp = compressor()
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
                                   compressors=compressor(), dimension_names=("sample",))
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
        if self._draws:
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
        self._dirty.add(i // BLOCK)

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
                lo, hi = blk * BLOCK, min((blk + 1) * BLOCK, n)
                self._arrays[name][lo:hi] = self._mem[name][lo:hi]
        self._dirty.clear()

def _root_attributes(config: Config, plan: SamplePlan, scenario) -> dict:
    """The root attributes of a new store (see :mod:`.schema`)."""
    default = DatasetConfig()
    recorded = dataclasses.replace(config, dataset=dataclasses.replace(config.dataset, workers=default.workers,
                                                                       scheduler=default.scheduler))
    return {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "versions": package_versions(), "config_toml": config_to_toml(recorded, comments=False),
        "mesh_fingerprint": scenario.mesh.fingerprint(),
        "n_samples": plan.n_samples, "n_lbo": plan.n_lbo, "n_test2": plan.n_samples - plan.n_lbo,
        "split_labels": {str(k): v for k, v in SPLIT_NAMES.items()},
        "status_labels": {str(k): v for k, v in STATUS_NAMES.items()},
        "units": {"length": "mm", "force": "N", "stress": "MPa"},
        "calibration": None, "failures": {},
        "scenario": json.loads(json.dumps(scenario.summary(), default=float)),
    }


def _put_setup(root, markers, scenario) -> None:
    """Store the set-up arrays of a new store: mesh, markers, supported vertices, LBO basis
    and the scenario's arrays."""
    comp = compressor()

    def put(name, data):
        data = np.ascontiguousarray(data)
        chunks = tuple(max(1, d) for d in data.shape) or None  # an empty array still needs a chunk
        a = root.create_array(name, shape=data.shape, dtype=data.dtype, chunks=chunks, compressors=comp)
        a[...] = data

    mesh, basis = scenario.mesh, scenario.surface_forces.basis
    put("mesh/points", np.asarray(mesh.points, dtype=np.float64))
    put("mesh/tets", np.asarray(mesh.tets, dtype=np.int64))
    put("markers", np.asarray(markers, dtype=np.int64))
    put("fixed", np.asarray(scenario.supported, dtype=np.int64))
    put("lbo/vertices", np.asarray(basis.vertices, dtype=np.int64))
    put("lbo/vectors", np.asarray(basis.vectors, dtype=np.float64))
    put("lbo/eigenvalues", np.asarray(basis.eigenvalues, dtype=np.float64))
    put("lbo/mass", np.asarray(basis.mass, dtype=np.float64))
    for name, data in scenario.arrays().items():
        put(f"scenario/{name}", data)


def _create_sample_arrays(root, plan: SamplePlan, scenario) -> None:
    """The per-sample arrays of a new store (the draw arrays when the scenario draws per
    sample), with the plan's betas, seeds and splits."""
    comp = compressor()
    n, nv, nb = plan.n_samples, scenario.mesh.n_vertices, scenario.surface_forces.basis.vectors.shape[1]
    s = root.create_group("samples")
    s.create_array("displacements", shape=(n, nv, 3), dtype="float32", chunks=(1, nv, 3),
                   fill_value=np.nan, compressors=comp, dimension_names=("sample", "vertex", "axis"))
    s.create_array("forces", shape=(n, nv, 3), dtype="float32", chunks=(1, nv, 3), fill_value=0.0,
                   compressors=comp, dimension_names=("sample", "vertex", "axis"))
    s.create_array("weights", shape=(n, nb, 3), dtype="float64", chunks=(BLOCK, nb, 3), fill_value=np.nan,
                   compressors=comp, dimension_names=("sample", "basis", "axis"))
    for name, (dtype, fill) in SCALARS.items():
        s.create_array(name, shape=(n,), dtype=dtype, chunks=(min(BLOCK, n),), fill_value=fill,
                       compressors=comp, dimension_names=("sample",))
    tables = ({**DRAWS} if scenario.draws_per_sample else {}) | (PARAMETERS if scenario.uncertain is not None else {})
    for instrument in scenario.config.instruments:
        tables |= instrument_arrays(instrument.name)
    for name, (shape, dtype, fill) in tables.items():
        s.create_array(name, shape=(n, *shape), dtype=dtype, chunks=(min(BLOCK, n), *shape),
                       fill_value=fill, compressors=comp, dimension_names=("sample",) + (("axis",) if shape else ()))
    s["beta"][:] = plan.beta
    s["seed"][:] = plan.seed
    s["split"][:] = plan.split


# ---------------------------------------------------------------- compatibility of a store
_DATA_SECTIONS = ("mesh", "markers", "material", "solver", "forces", "dataset", "scenario")


def data_config(cfg: Config) -> dict:
    """The part of a config that determines a data set's contents (nested dict): of
    ``[dataset]`` its :class:`~tissuecast.config.DatasetContent` (run settings may differ when
    resuming); of ``[mesh]`` all but ``path`` (the file may move: its content is checked by
    fingerprint instead, :func:`_check_mesh`); ``[markers]`` only where the pins are chosen
    around the markers (``scenario.pins``): without pins the markers change no sample, so a
    store resumes (and a model trains on it) with other markers, e.g. planned ones."""
    d = config_to_dict(cfg)
    out = {sec: dict(d[sec]) for sec in _DATA_SECTIONS}
    if not cfg.scenario.pins:
        out["markers"] = {}
    out["dataset"] = config_to_dict(cfg.dataset.content())
    out["mesh"].pop("path")
    # an instrument's OpenIGTLink device name is for serving: it changes no number of the data set
    out["scenario"]["instruments"] = [{k: v for k, v in i.items() if k != "device"}
                                      for i in out["scenario"].get("instruments", [])]
    return out


def data_differences(first: dict, second: dict, sections=_DATA_SECTIONS) -> list[tuple[str, object, object]]:
    """``[(section.key, first's value, second's value)]`` where two :func:`data_config` dicts
    differ in ``sections`` (a key one of them lacks: None there), sorted by key within a section."""
    return [(f"{sec}.{k}", first[sec].get(k), second[sec].get(k))
            for sec in sections for k in sorted(set(first[sec]) | set(second[sec]))
            if first[sec].get(k) != second[sec].get(k)]


def _check_config(writer: StoreWriter, cfg: Config) -> None:
    """Refuse data settings other than the store's (batch settings once its batches are fixed excepted)."""
    stored = data_config(config_from_dict(tomllib.loads(writer.config_toml)))
    now = data_config(cfg)
    if writer.batches is not None:  # the store's own batches decide from here on (.batch)
        for key in ("batch_size", "batch_memory"):
            stored["dataset"].pop(key, None)
            now["dataset"].pop(key, None)
    diffs = [f"{key}: {a!r} in the store, {b!r} now" for key, a, b in data_differences(stored, now)]
    if diffs:
        raise DatasetError(
            f"data set {str(writer.path)!r} was made with a different configuration ({'; '.join(diffs[:4])}"
            f"{'; ...' if len(diffs) > 4 else ''}); continue it with its own config (`tissuecast simulate STORE`; "
            "`tissuecast config show STORE` prints it) or choose another --store path; a store is never overwritten")


def _check_mesh(writer: StoreWriter, mesh) -> None:
    """Refuse a mesh other than the store's (by fingerprint)."""
    fp = writer.root.attrs.get("mesh_fingerprint")
    if fp != mesh.fingerprint():
        raise DatasetError(
            f"data set {str(writer.path)!r} was made on a different mesh (fingerprint {str(fp)[:12]}..., this mesh "
            f"{mesh.fingerprint()[:12]}...); use the original mesh or another --store path; a store is never overwritten")


def _check_ids(writer: StoreWriter, cfg: Config, markers: np.ndarray, fixed: np.ndarray) -> None:
    """Refuse markers (with pins) or supported vertices other than the store's."""
    for what, now in (("markers", markers), ("fixed", fixed)):
        stored_ids = np.asarray(writer.read(what), dtype=np.int64)
        if np.array_equal(stored_ids, now):
            continue
        if what == "markers" and not cfg.scenario.pins:
            # without pins the markers do not enter the simulation (pins are chosen around them):
            # the store keeps the markers it was made with; training takes the config's
            # (tissuecast.app.pipeline.train_from_store)
            log.info("data set %r was made with markers %s, this config chooses %s; the store keeps its own, "
                     "a model trained from this config uses the config's", str(writer.path), stored_ids.tolist(),
                     np.asarray(now).tolist())
            continue
        raise DatasetError(
            f"data set {str(writer.path)!r} has {what} vertices {stored_ids.tolist()} but this config gives "
            f"{np.asarray(now).tolist()} (e.g. a store from a version with another marker or pin rule), and "
            f"{'the pins are chosen around the markers' if what == 'markers' else 'the fixed vertices'} change the "
            "simulated fields: continue it with the tissuecast version that made it, or choose another --store path "
            "(a store is never overwritten)")


def _check_springs(writer: StoreWriter, scenario) -> None:
    """Warn when a store's springs differ from those its config gives now (a store from a
    version that lumped P2 springs by ``integral(N_a) dA`` only); its workers go on with the
    stored springs (:meth:`~.reader.Dataset.recipe`)."""
    stored = read_scenario_arrays(writer.root)
    springs = scenario.springs
    if "spring_nodes" not in stored or springs is None:
        return
    if np.array_equal(stored["spring_nodes"], springs.nodes) and np.allclose(stored["spring_stiffness"],
                                                                            springs.stiffness, rtol=1e-12, atol=0.0):
        return
    log.warning("data set %r holds springs other than this config gives (%d nodes, now %d: e.g. made before P2 "
                "springs were lumped HRZ-style by default); it goes on with its own springs, so its samples stay "
                "one data set",
                str(writer.path), len(stored["spring_nodes"]), len(springs.nodes))


def _draw_values(draw) -> dict:
    """A :class:`~tissuecast.scenario.ScenarioDraw` as the values of the :data:`DRAWS` arrays."""
    out = {}
    if draw.gravity_direction is not None:
        out["gravity_direction"] = draw.gravity_direction
    ind = draw.indentation
    if ind is not None:
        out.update(indent_centre=ind.centre, indent_depth=ind.depth, indent_slide=ind.slide,
                   indent_displacement=ind.displacement)
    if draw.parameters is not None:
        out.update({f"param_{k}": v for k, v in draw.parameters.record().items()})
    for name, pose in draw.instruments:
        out.update({f"{INSTRUMENT_PREFIX}{name}_tip": pose.tip, f"{INSTRUMENT_PREFIX}{name}_direction": pose.direction,
                    f"{INSTRUMENT_PREFIX}{name}_depth": pose.depth, f"{INSTRUMENT_PREFIX}{name}_contact": int(pose.contact)})
    return out


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
