"""The data-set store's schema: one Zarr v3 directory per data set, readable with zarr alone.

This module holds the layout (below), the tables of per-sample arrays, the schema check and
the readers of the set-up arrays that the writer (:mod:`.store`) and the reader
(:mod:`.reader`) share.

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
                                    before scenarios existed (they are the paper's: pins + LBO;
                                    their ``fixed`` vertices are the pins)
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
                            work (then zero), 3 a calibration pilot's solution of the previous round,
                            4 a basis sample's interim-model prediction, 5 a first-round pilot's
                            own linear answer
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
      samples/indent_displacement (N, 3) float64 mm, the tool tip's displacement (every patch
                            vertex's with a flat tool)
      samples/param_youngs_modulus, param_density, param_spring_normal, param_spring_tangential
                            (N,) float64 the sample's drawn factors on E, the density and the
                            springs' stiffnesses; samples/param_poisson_ratio (N,) float64 its
                            nu (NaN: the nominal ones); samples/param_attached_margin (N,) float64
                            mm the attached region's growth along the surface (negative: shrink)
                            (with [scenario.uncertain]; a function of the seed:
                            scenario.parameters.parameter_rng)
      samples/instrument_<name>_tip, samples/instrument_<name>_direction (N, 3) float64 the
                            tracked instrument's tip (mm, mesh frame) and unit push direction
                            (NaN: away from the tissue, or pending); samples/instrument_<name>_depth
                            (N,) float64 mm below the reference surface (0 when away);
                            samples/instrument_<name>_contact (N,) int8 1 touching, 0 away, -1
                            pending (with [[scenario.instruments]]; tissuecast.instruments)
      scenario/attached_distance (n_v,) float64 mm signed distance along the surface from the
                            nominal attached region's rim (with an uncertain attached margin;
                            scenario/attached is then the region at its smallest extent)
      scenario/spring_normal_part, scenario/spring_tangential_part (s, 3, 3) float64 N/mm the
                            springs' normal and tangential stiffness (with uncertain springs)
      (every store has the scenario/ group, the paper's set-up too, except stores made before
      scenarios existed; the samples' draw arrays exist in stores whose scenario draws them;
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

Chunks are compressed with Blosc/zstd; how they are written: :mod:`.store`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DatasetError, require
from .codes import InitialGuess, SampleStatus

__all__ = ["SCHEMA", "SCHEMA_VERSION", "SCALARS", "DRAWS", "PARAMETERS", "INSTRUMENT_PREFIX", "POSE_PARTS",
           "instrument_arrays", "check_schema", "open_root", "open_store_root", "read_lbo_basis", "read_scenario_arrays"]

SCHEMA = "tissuecast.dataset"
SCHEMA_VERSION = 1
BLOCK = 256  # chunk length of the per-sample 1-D arrays and weights

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
ADDED_LATER = ("predicted",)  # per-sample arrays that stores of earlier releases lack (created on open)
#: Per-sample scenario draws: name -> (trailing shape, dtype, fill value), in stores whose
#: scenario draws a gravity direction or an indentation.
DRAWS = {
    "gravity_direction": ((3,), "float64", np.nan),
    "indent_centre": ((), "int64", -1),
    "indent_depth": ((), "float64", np.nan),
    "indent_slide": ((), "float64", np.nan),
    "indent_displacement": ((3,), "float64", np.nan),
}
#: Per-sample uncertain parameters (``samples/param_<name>``), in stores whose scenario draws
#: them (``[scenario.uncertain]``): name -> (trailing shape, dtype, fill value).
PARAMETERS = {f"param_{name}": ((), "float64", np.nan) for name in
              ("youngs_modulus", "poisson_ratio", "density", "spring_normal", "spring_tangential", "attached_margin")}


#: Per-sample poses of a tracked instrument (``samples/instrument_<name>_<part>``), in stores
#: whose scenario declares instruments: part -> (trailing shape, dtype, fill value).
INSTRUMENT_PREFIX = "instrument_"
POSE_PARTS = {"tip": ((3,), "float64", np.nan), "direction": ((3,), "float64", np.nan), "depth": ((), "float64", np.nan),
              "contact": ((), "int8", -1)}


def instrument_arrays(name: str) -> dict:
    """The per-sample pose arrays of instrument ``name``: array name -> (trailing shape, dtype, fill)."""
    return {f"{INSTRUMENT_PREFIX}{name}_{part}": spec for part, spec in POSE_PARTS.items()}


def zarr_module():
    """The zarr package (a clear error naming the extra when it is missing)."""
    return require("zarr", "data", "data-set stores")


def compressor():
    """The chunks' codec: Blosc with zstd, byte shuffle."""
    return zarr_module().codecs.BloscCodec(cname="zstd", clevel=5, shuffle="shuffle")


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


def read_scenario_arrays(root) -> dict[str, np.ndarray]:
    """The resolved scenario's stored arrays (``scenario/*``: pins, attached region, springs,
    materials, indentation access; :func:`tissuecast.scenario.restore_scenario` rebuilds the
    scenario from them) of a store's root group. A store made before scenarios were recorded
    holds the paper's set-up: its ``fixed`` vertices are the pins, with no attached region and
    no elastic support."""
    if "scenario" not in root:
        none = np.zeros(0, dtype=np.int64)
        return {"pinned": np.asarray(root["fixed"][...], dtype=np.int64), "attached": none, "spring_region": none}
    group = root["scenario"]
    return {name: np.asarray(group[name][...]) for name in group.array_keys()}


def open_root(path: Path):
    """The store's root Zarr group, read-only, its schema checked.

    Raises:
        DatasetError: as :func:`~.reader.open_dataset`.
    """
    root = open_store_root(Path(path), mode="r")
    check_schema(root, Path(path))
    return root


def open_store_root(path: Path, mode: str):
    """The store's root Zarr group opened with ``mode`` (``"r"`` or ``"r+"``), not yet schema-checked.

    Raises:
        DatasetError: the path is missing, not a Zarr v3 store, or cannot be opened.
    """
    zarr = zarr_module()
    if not path.exists():
        raise DatasetError(f"data set {str(path)!r} does not exist; create it with `tissuecast simulate CONFIG --store {path}`")
    if not (path / "zarr.json").is_file():
        raise DatasetError(f"{str(path)!r} is not a Zarr v3 store (no zarr.json); is it a tissuecast data set?")
    try:
        return zarr.open_group(zarr.storage.LocalStore(path, read_only=(mode == "r")), mode=mode)
    except (ValueError, KeyError, OSError, TypeError) as exc:
        raise DatasetError(f"cannot open data set {str(path)!r}: {exc}") from exc
