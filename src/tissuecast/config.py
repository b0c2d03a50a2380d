"""Run configuration: frozen dataclasses loaded from TOML, with the paper's values as defaults.

One :class:`Config` drives a whole run; each pipeline stage reads its own section. Loading is
strict: an unknown key, a value of the wrong type or a value out of its range raises
:class:`~tissuecast.errors.ConfigError` naming the key (``section.key``) and what is allowed.

Units: lengths in mm, forces in N, stresses and moduli in MPa (E = 21 kPa is 0.021 MPa).
Vertex ids are 0-based (the paper's vertex 97 is ``start = 96`` here).
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import ConfigError

__all__ = [
    "Config",
    "MeshConfig",
    "MarkerConfig",
    "MaterialConfig",
    "SolverConfig",
    "ForceConfig",
    "DatasetConfig",
    "DatasetContent",
    "RunSettings",
    "SurrogateConfig",
    "EvaluateConfig",
    "TargetConfig",
    "ServeConfig",
    "ScenarioConfig",
    "RegionConfig",
    "ANATOMICAL_DIRECTIONS",
    "SpringConfig",
    "GravityConfig",
    "IndentationConfig",
    "MaterialRegionConfig",
    "MaterialRegionsConfig",
    "UncertainConfig",
    "InstrumentConfig",
    "load_config",
    "config_from_dict",
    "config_to_dict",
    "config_to_toml",
    "with_overrides",
    "nothing_drawn",
]


def _f(default, *, lo=None, hi=None, lo_open=False, hi_open=False, choices=None, doc=""):
    """A dataclass field carrying its validation rule in metadata."""
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "choices": choices, "doc": doc}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults")
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class MeshConfig:
    """Where the tetrahedral mesh comes from."""

    path: str = _f("", doc="mesh file, closed surface file, or label map (.nii, .nii.gz, .nrrd, .seg.nrrd: meshed in the scan's LPS frame); empty = the built-in phantom")
    units: str = _f("mm", choices=("mm", "cm", "m"), doc="length unit of the file (label maps: always their own physical units, mm)")
    surface_mesh_size: float = _f(3.0, lo=0.0, lo_open=True, doc="target tet size (mm) when tetrahedralising a surface or a label map")
    label: int = _f(0, lo=0, doc="label map: voxel value to mesh; 0 = the only non-zero value of the map")
    segment: str = _f("", doc="3D Slicer segmentation (.seg.nrrd): segment name or ID to mesh; empty = by label, or the only segment")
    keep_largest: bool = _f(False, doc="label map: keep the largest face-connected piece of the label instead of refusing several")
    fill_cavities: bool = _f(False, doc="label map: fill background enclosed by the label instead of refusing it")
    smoothing_iterations: int = _f(30, lo=0, hi=1000, doc="label map: Taubin (non-shrinking) smoothing passes of the marching-cubes surface")
    max_vertices: int = _f(0, lo=0, doc="label map or closed surface: at most this many vertices, the edge length searched (surface_mesh_size unused); 0 = no budget")


#: Fixed-vertex placement rules (see :func:`tissuecast.scenario.pins.select_fixed_vertices`).
FIXED_RULES = ("compact", "spread")
#: How the markers a model reads are chosen (``markers.rule``).
MARKER_RULES = ("k-center", "planned")


@dataclass(frozen=True)
class MarkerConfig:
    """Fiducial markers (revised k-center clustering, or planned from the simulations) and fixed vertices."""

    count: int = _f(5, lo=1, hi=200, doc="number of fiducial markers n_d")
    start: int = _f(96, lo=0, doc="0-based start vertex v0 (paper: 97 1-based)")
    min_distance: float = _f(10.0, lo=0.0, doc="d_min in mm")
    ids: tuple[int, ...] = _f((), doc="user-given 0-based marker ids (overrides count/start and rule)")
    rule: str = _f("k-center", choices=MARKER_RULES, doc="'k-center' = the paper's rule (count, start, min_distance); 'planned' = count surface markers planned from the simulations before training")
    sentinel: bool = _f(True, doc="rule 'planned', attached_margin drawn: the last marker is a sentinel beyond the drawn range; if it stands still the alarm says so")
    fixed_count: int = _f(3, lo=1, hi=50, doc="number of fixed (pinned) vertices")
    fixed_ids: tuple[int, ...] = _f((), doc="user-given 0-based fixed vertex ids")
    fixed_depth_fraction: float = _f(0.5, lo=0.0, hi=1.0, doc="fixed vertices lie at least this share of the largest depth below the surface")
    fixed_rule: str = _f("compact", choices=FIXED_RULES, doc="fixed-vertex rule: 'compact' = a small pinned triangle deep inside, 'spread' = as far apart as possible")
    fixed_spacing: float = _f(5.0, lo=0.0, lo_open=True, doc="smallest distance (mm) between compact fixed vertices")


@dataclass(frozen=True)
class MaterialConfig:
    """Compressible neo-Hookean material (Abaqus/CalculiX NEO HOOKE form)."""

    youngs_modulus: float = _f(0.021, lo=0.0, lo_open=True, doc="E in MPa (21 kPa = 0.021 MPa)")
    poisson_ratio: float = _f(0.45, lo=-1.0, hi=0.5, lo_open=True, hi_open=True, doc="nu")
    check_range: bool = _f(True, doc="refuse moduli outside soft tissue's 0.0001-1 MPa (a unit slip); false for stiffer phantoms or materials")


@dataclass(frozen=True)
class SolverConfig:
    """Nonlinear FEM solver settings."""

    order: int = _f(2, choices=(1, 2), doc="element order: 2 = quadratic 10-node tets (C3D10)")
    linear_solver: str = _f("auto", choices=("auto", "cholmod", "pardiso", "superlu", "p-multigrid"), doc="linear solves: a sparse direct backend, or 'p-multigrid' (a two-level multigrid cycle preconditioning conjugate gradients, cost growing like the mesh); auto = p-multigrid for P2 meshes of at least multigrid_dofs free dofs, else the fastest direct backend")
    multigrid_dofs: int = _f(40000, lo=0, doc="linear_solver auto: use p-multigrid from this many free dofs on (P2 only); 0 = never")
    multigrid_smoothing: int = _f(2, lo=1, hi=8, doc="p-multigrid: Chebyshev-Jacobi smoothing steps before and after the coarse (P1) correction")
    force_tolerance: float = _f(5e-3, lo=0.0, lo_open=True, hi=1.0, doc="residual norm / reference force norm")
    displacement_tolerance: float = _f(1e-2, lo=0.0, lo_open=True, hi=1.0, doc="correction / increment norm")
    initial_increment: float = _f(
        0.5,
        lo=0.0,
        lo_open=True,
        hi=1.0,
        doc="first load fraction of a cold start (a solve with an initial guess starts at the full load)",
    )
    min_increment: float = _f(1e-5, lo=0.0, lo_open=True, hi=1.0, doc="smallest load fraction before giving up")
    max_increments: int = _f(200, lo=1, doc="maximum number of increments")
    max_iterations: int = _f(30, lo=1, doc="Newton iterations per increment before cutting back")
    retries: int = _f(1, lo=0, hi=10, doc="retries of a failed sample with more cautious increments")
    strategy: str = _f(
        "krylov",
        choices=("newton", "quasi-newton", "krylov"),
        doc="newton: factorise every tangent; quasi-newton: reuse the last factorisation; krylov: CG preconditioned by the last factorisation",
    )
    krylov_iterations: int = _f(20, lo=1, hi=1000, doc="krylov: most conjugate-gradient steps per Newton iteration before refactorising")
    krylov_tolerance: float = _f(5e-2, lo=0.0, lo_open=True, hi=0.5, doc="krylov: relative residual that ends the conjugate gradients (an inexact Newton direction)")
    krylov_recycle: int = _f(20, lo=0, hi=200, doc="krylov: most CG directions of the solve's earlier Newton iterations kept to deflate the next ones; 0 = plain preconditioned CG")
    reference_preconditioner: bool = _f(True, doc="krylov, solves with a guess: precondition with the stiffness at zero displacement (factorised once per Solver), co-rotated")
    rotation_aware: bool = _f(True, doc="line search moves the rigid-rotation part of each step along an arc (large swings about the fixed vertices)")
    refactor_ratio: float = _f(0.5, lo=0.0, hi=1.0, doc="quasi-newton: refactorise when an iteration reduced the residual norm by less than this factor")
    max_quasi_newton: int = _f(2, lo=1, doc="quasi-newton: refactorise after this many iterations with a reused factorisation")
    grow_iterations: int = _f(6, lo=1, doc="grow the next increment 1.5x when one converged within this many iterations")


@dataclass(frozen=True)
class ForceConfig:
    """Random surface force fields (LBO training fields and test-2 LSC fields)."""

    n_basis: int = _f(20, lo=1, hi=500, doc="number of smoothest LBO eigenvectors")
    target_max_displacement: float = _f(30.0, lo=0.0, lo_open=True, doc="largest displacement (mm) the data set should reach")
    lsc_points: int = _f(3, lo=1, hi=50, doc="concentrated forces per test-2 sample")
    lsc_iterations: int = _f(20, lo=0, hi=10000, doc="local Laplacian smoothing iterations")
    lsc_rate: float = _f(0.1, lo=0.0, lo_open=True, hi=1.0, doc="smoothing rate gamma")
    betas: tuple[float, ...] = _f((0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0), doc="LBO share beta of test-2 fields")
    loading: str = _f("nodal", choices=("nodal", "traction"), doc="nodal = forces on the vertices (the paper); traction = field / vertex area as a surface traction, no point loads (docs/scenarios.md)")


@dataclass(frozen=True)
class DatasetContent:
    """The ``[dataset]`` settings that decide a store's content (its samples and their numbers):
    a store resumes only with the same values (batch settings excepted once its batches are
    fixed). Read from a section with :meth:`DatasetConfig.content`."""

    n_samples: int
    split: tuple[float, ...]
    n_test2: int
    seed: int
    alpha: float
    calibration_samples: int
    calibration_quantile: float
    predictor: str
    predictor_samples: int
    predictor_tolerance: float
    batch_size: int
    batch_memory: float


@dataclass(frozen=True)
class RunSettings:
    """The ``[dataset]`` settings of how one run goes (where the store is, who solves, when a
    slow attempt stops): they change no number of a store and may differ when it resumes.
    Read from a section with :meth:`DatasetConfig.run_settings`."""

    store: str
    workers: int
    scheduler: str
    time_budget: float
    time_budget_min: float


@dataclass(frozen=True)
class DatasetConfig:
    """Data-set generation: one TOML section, two groups of keys. The keys of
    :class:`DatasetContent` decide the store's content; those of :class:`RunSettings` only how
    a run goes (:meth:`content`, :meth:`run_settings`)."""

    store: str = _f("dataset.zarr", doc="path of the store")
    n_samples: int = _f(2000, lo=1, doc="number of LBO samples (train + valid + test-1)")
    split: tuple[float, ...] = _f((8.0, 1.0, 1.0), doc="train : valid : test-1 ratio")
    n_test2: int = _f(200, lo=0, doc="number of test-2 (LSC/beta) samples")
    seed: int = _f(0, lo=0, doc="base seed; per-sample seeds derive from it and the index")
    workers: int = _f(0, lo=0, hi=256, doc="local worker processes; 0 = one per usable CPU, no more than the available memory holds at batch_memory each")
    scheduler: str = _f("", doc="Dask scheduler address tcp://HOST:PORT; empty = local")
    alpha: float = _f(0.0, lo=0.0, doc="LBO force magnitude alpha (N); 0 = calibrate to forces.target_max_displacement")
    calibration_samples: int = _f(24, lo=1, hi=1000, doc="pilot samples of the force-magnitude calibration")
    calibration_quantile: float = _f(0.9, lo=0.0, hi=1.0, doc="quantile of per-sample max displacement that meets the target")
    predictor: str = _f("reduced", choices=("reduced", "none"), doc="initial guess of each solve: reduced = a reduced-order model of the first predictor_samples solutions; none = zero")
    predictor_samples: int = _f(40, lo=2, hi=100000, doc="the first LBO samples (ids 0..n-1), solved from zero, whose solutions build the reduced model")
    predictor_tolerance: float = _f(0.01, lo=0.0, lo_open=True, hi=0.5, doc="ECSW hyper-reduction: relative error of the reduced internal forces")
    batch_size: int = _f(16, lo=1, hi=256, doc="samples a worker solves together once the reduced model exists (their solves with the shared reference factorisation gathered: Solver.solve_batch); 1 = one at a time; the last bits of a sample depend on its batch")
    batch_memory: float = _f(4.0, lo=0.0, lo_open=True, doc="GiB a worker's batch may hold: batch_size is cut so that its samples' tangents fit (large meshes)")
    time_budget: float = _f(10.0, lo=0.0, doc="a solver attempt running longer than this many times the running median of its phase's samples is stopped (the sample goes on with its cautious retries, else is recorded failed); 0 = no budget")
    time_budget_min: float = _f(60.0, lo=0.0, doc="the time budget is at least this many seconds (machine hiccups never stop a sample)")

    def content(self) -> DatasetContent:
        """The settings that decide the store's content."""
        return DatasetContent(**{f.name: getattr(self, f.name) for f in dataclasses.fields(DatasetContent)})

    def run_settings(self) -> RunSettings:
        """The settings of how a run goes (they may change between runs on one store)."""
        return RunSettings(**{f.name: getattr(self, f.name) for f in dataclasses.fields(RunSettings)})


#: Rules choosing the number of PCA components (see :class:`SurrogateConfig`).
PCA_RULES = ("validation", "paper")
#: Learning-rate schedules and PCA-weight scalings of the MLP's training (see :mod:`tissuecast.surrogate.mlp`).
SCHEDULES = ("onecycle", "cosine", "constant")
OUTPUT_SCALINGS = ("global", "component")


#: How the surrogate maps markers to PCA weights (see :mod:`tissuecast.surrogate.head`).
HEADS = ("quadratic", "none")
#: How the error bounds and the alarm are calibrated (see :mod:`tissuecast.surrogate.cross_calibration`).
CALIBRATIONS = ("cross-validation", "split", "none")
#: How the predicted coefficients become the field (see :mod:`tissuecast.surrogate.decoder`).
DECODERS = ("pca", "local")
#: Hidden-layer nonlinearities of the surrogate's networks.
ACTIVATIONS = ("relu", "silu")


@dataclass(frozen=True)
class SurrogateConfig:
    """PCA + MLP surrogate and the ridge baseline."""

    n_components: int = _f(0, lo=0, doc="PCA components n_w; 0 = chosen by pca_rule")
    pca_rule: str = _f("validation", choices=PCA_RULES, doc="n_w when n_components = 0: 'validation' = lowest validation mean Offset_max of the trained model; 'paper' = the pca_max_error rule")
    pca_max_components: int = _f(128, lo=1, hi=1000, doc="validation rule: the network is trained on this many components, then truncated")
    pca_max_error: float = _f(1.0, lo=0.0, lo_open=True, doc="paper rule: max cross-validated vertex reconstruction error (mm)")
    pca_folds: int = _f(5, lo=2, hi=50, doc="paper rule: folds of the n_w cross-validation")
    hidden: tuple[int, ...] = _f((128, 64), doc="hidden layer widths")
    activation: str = _f("relu", choices=ACTIVATIONS, doc="hidden-layer nonlinearity: 'relu' (the paper's) or 'silu' (x sigmoid(x), smooth: for sensitivity_weight > 0)")
    head: str = _f("quadratic", choices=HEADS, doc="'quadratic' = a regression on linear and quadratic marker features predicts, the networks learn its residual; 'none' = networks alone")
    head_dims: int = _f(0, lo=0, hi=60, doc="quadratic head: input directions whose products are features; 0 = chosen on validation")
    decoder: str = _f("pca", choices=DECODERS, doc="'pca' = the PCA basis decodes the predicted weights; 'local' = the PCA basis plus region-wise components of its residual")
    decoder_regions: int = _f(8, lo=1, hi=100000, doc="decoder 'local': regions of nearby vertices the mesh is cut into, each with its own residual components")
    decoder_components: int = _f(384, lo=1, hi=5000, doc="decoder 'local': local components kept over all regions (largest singular values of the residual first)")
    epochs: int = _f(2500, lo=1, doc="maximum training epochs")
    fallback_epochs: int = _f(0, lo=0, doc="tracked instruments: epochs of the markers-only fallback (it answers while tracking is lost); 0 = epochs")
    batch_size: int = _f(128, lo=1, doc="mini-batch size")
    learning_rate: float = _f(3e-3, lo=0.0, lo_open=True, hi=1.0, doc="Adam (peak) learning rate")
    patience: int = _f(250, lo=0, doc="early-stopping patience in epochs; 0 = off")
    noise_sigma: float = _f(0.0, lo=0.0, doc="marker noise augmentation (mm)")
    ridge_ratio: float = _f(1e-3, lo=0.0, doc="ridge a2/a1")
    seed: int = _f(0, lo=0, doc="training seed")
    threads: int = _f(2, lo=1, hi=256, doc="torch threads a network trains on; the same count gives the same weights bit for bit (another may round differently)")
    schedule: str = _f("onecycle", choices=SCHEDULES, doc="learning-rate schedule")
    output_scaling: str = _f("global", choices=OUTPUT_SCALINGS, doc="PCA-weight scaling of the loss")
    weight_decay: float = _f(0.0, lo=0.0, doc="Adam weight decay")
    marker_dropout: float = _f(0.0, lo=0.0, hi=1.0, doc="share of training samples with one marker hidden; > 0 enables missing-marker input")
    sensitivity_weight: float = _f(0.0, lo=0.0, doc="weight in the loss of the field's derivatives along each sample's load directions (docs/surrogate.md); 0 = off; P1 and marker_dropout = 0 only")
    sensitivity_directions: int = _f(4, lo=1, hi=64, doc="sensitivity_weight > 0: load directions drawn per sample in each mini-batch step")
    ensemble: int = _f(1, lo=1, hi=64, doc="networks trained with different seeds (>= 2 gives uncertainty)")
    calibration: str = _f("split", choices=CALIBRATIONS, doc="error bounds and alarm calibrated on out-of-fold predictions (cross-validation), on calibration_share held out (split), or none")
    calibration_folds: int = _f(5, lo=2, hi=50, doc="calibration = 'cross-validation': folds of the training split (one more model trained per fold)")
    calibration_fold_ensemble: int = _f(0, lo=0, hi=64, doc="calibration = 'cross-validation': networks per fold model; 0 = surrogate.ensemble")
    calibration_share: float = _f(0.125, lo=0.0, hi=0.5, hi_open=True, doc="calibration = 'split': share of the training split held out (seeded) to calibrate bounds and alarm; 0 = neither")
    coverage: float = _f(0.9, lo=0.0, hi=1.0, lo_open=True, hi_open=True, doc="nominal coverage of the per-vertex error bounds: each vertex's error is below its bound with at least this probability")
    false_alarm_rate: float = _f(0.01, lo=0.0, hi=1.0, lo_open=True, hi_open=True, doc="share of in-distribution inputs allowed to raise the out-of-distribution alarm")
    alarm_fault_score: bool = _f(False, doc="the alarm also tests for one displaced marker: catches it sooner with many markers, catches fewer of the other faults at the same false-alarm rate")
    nominal_expert: bool = _f(False, doc="run: also a nominal store (STORE_nominal) and a nominal-only expert on the model's markers, a gate routing each field (docs/uncertainty.md)")
    nominal_samples: int = _f(0, lo=0, doc="nominal_expert: the nominal store's n_samples (it has no test-2); 0 = dataset.n_samples")


#: Where the errors at targets (TRE) are measured (see :mod:`tissuecast.evaluate.targets`).
TARGET_RULES = ("interior", "tag", "label", "points")


@dataclass(frozen=True)
class TargetConfig:
    """Targets: the points inside the tissue where the clinic measures the error (TRE)."""

    rule: str = _f("interior", choices=TARGET_RULES, doc="interior = `count` deep vertices spread by k-center; tag = a mesh region's vertices; label = `count` points of a label-map label; points = `path`'s")
    count: int = _f(10, lo=1, hi=10000, doc="rules 'interior' and 'label': number of targets")
    depth: float = _f(0.0, lo=0.0, doc="rule 'interior': least distance (mm) from the outer surface; 0 = half the deepest vertex's")
    tag: str = _f("", doc="rule 'tag': name of a point-data array, point set, cell set or cell-data array of the mesh file")
    tag_value: int = _f(-1, doc="rule 'tag' on a data array: the value marking the region; -1 = any non-zero value")
    path: str = _f("", doc="rule 'label': a label map (.nii[.gz], .nrrd, .seg.nrrd); rule 'points': CSV (x, y, z or label, x, y, z; LPS mm) or Slicer .mrk.json / .fcsv")
    label: int = _f(0, lo=0, doc="rule 'label': voxel value of the region; 0 = the only non-zero value of the map")
    segment: str = _f("", doc="rule 'label' on a 3D Slicer segmentation (.seg.nrrd): segment name or ID")


@dataclass(frozen=True)
class EvaluateConfig:
    """Evaluation and report."""

    output: str = _f("report", doc="report folder")
    renders: int = _f(3, lo=0, hi=100, doc="number of samples rendered in 3D")
    targets: TargetConfig = field(default_factory=TargetConfig, metadata={"doc": "where target registration errors (TRE) are measured"})


#: How TRANSFORM marker input triggers predictions, and the frames a client may work in
#: (see :mod:`tissuecast.serve.session`, :mod:`tissuecast.serve.client_frames`).
TRANSFORM_MODES = ("frame", "each")
CLIENT_FRAMES = ("LPS", "RAS")
SERVE_METHODS = ("mlp", "rigid")


@dataclass(frozen=True)
class ServeConfig:
    """OpenIGTLink server."""

    host: str = _f("127.0.0.1", doc="bind address (localhost unless asked otherwise)")
    port: int = _f(18944, lo=1, hi=65535, doc="TCP port (OpenIGTLink default 18944)")
    full_field: bool = _f(False, doc="send the full vertex field (POLYDATA TissueField) after every surface")
    transform_mode: str = _f("frame", choices=TRANSFORM_MODES, doc="TRANSFORM input: predict once all markers are fresh (frame) or on every update (each)")
    max_marker_offset: float = _f(100.0, lo=0.0, lo_open=True, doc="reject markers farther than this (mm) from their reference position")
    client_timeout: float = _f(5.0, lo=0.0, lo_open=True, doc="seconds an incomplete message may wait for its remaining bytes")
    client_frame: str = _f("LPS", choices=CLIENT_FRAMES, doc="frame of replies, and of markers without registration: LPS = the model's (scan's), RAS = 3D Slicer's world (OpenIGTLinkIF)")
    tracker_to_client: tuple[float, ...] = _f((), doc="tracker -> client frame registration: a 4x4 matrix row by row (16 numbers, mm); empty = none; a TRANSFORM TrackerToRas replaces it")
    method: str = _f("mlp", choices=SERVE_METHODS, doc="prediction: the learned model (mlp) or the rigid registration of the markers (rigid, the fallback baseline)")
    instrument_timeout: float = _f(0.5, lo=0.0, lo_open=True, doc="seconds without an instrument's TRANSFORM after which predictions use the markers only (a STATUS says so)")


# ------------------------------------------------------------------- scenario
#: Rules selecting a region of the outer surface (see :mod:`tissuecast.scenario.regions`).
REGION_RULES = ("none", "surface", "ids", "tag", "normal", "distance", "markups", "extreme", "label")
#: Anatomical directions a region rule may name (``toward``), as LPS unit vectors.
ANATOMICAL_DIRECTIONS = {"left": (1.0, 0.0, 0.0), "right": (-1.0, 0.0, 0.0), "posterior": (0.0, 1.0, 0.0),
                         "anterior": (0.0, -1.0, 0.0), "superior": (0.0, 0.0, 1.0), "inferior": (0.0, 0.0, -1.0)}

#: Surroundings' stiffness per unit area (N/mm^3 = MPa/mm) of the default elastic support:
#: tissue of modulus E = 0.021 MPa over a length of about L = 10 mm, k = E / L.
DEFAULT_SUPPORT_STIFFNESS = 0.0021

#: Accepted span of the length E / k (mm) that a spring stiffness k per unit area implies for
#: the tissue's modulus E; outside it the value is almost surely in other units.
SUPPORT_LENGTH_SPAN = (0.01, 1.0e4)

#: Accepted densities (t/mm^3): soft tissues and bone lie in 0.9e-9 .. 2.1e-9.
DENSITY_SPAN = (1.0e-10, 1.0e-8)
#: Young's moduli of soft tissues, MPa (0.1 kPa: brain at its softest; 1 MPa: stiff fibrous
#: tissue): a value outside is almost surely a unit slip (21 for 21 kPa, 21000 for 21 kPa in Pa).
SOFT_TISSUE_MODULUS_SPAN = (1.0e-4, 1.0)


@dataclass(frozen=True)
class RegionConfig:
    """A set of outer-surface vertices chosen by one rule (e.g. where the tissue is attached)."""

    rule: str = _f("none", choices=REGION_RULES, doc="surface = all; ids; tag = a mesh-file region; normal; distance; markups = Slicer points; extreme = farthest along a direction; label (see docs)")
    ids: tuple[int, ...] = _f((), lo=0, doc="rule 'ids': 0-based vertex ids")
    tag: str = _f("", doc="rule 'tag': name of a point-data array, point set, cell set or cell-data array of the mesh file")
    tag_value: int = _f(-1, doc="rule 'tag' on a point-data or cell-data array: the value marking the region; -1 = any non-zero value")
    direction: tuple[float, ...] = _f((0.0, 0.0, -1.0), doc="rule 'normal': direction (mesh coordinates) the region's outward normals point to")
    angle: float = _f(45.0, lo=0.0, hi=180.0, doc="rule 'normal': largest angle in degrees between a vertex's outward normal and `direction`")
    point: tuple[float, ...] = _f((0.0, 0.0, 0.0), doc="rule 'distance': centre, mm (mesh coordinates)")
    distance: float = _f(10.0, lo=0.0, lo_open=True, doc="rules 'distance', 'markups', 'extreme': radius around the point, mm")
    toward: str = _f("", choices=("",) + tuple(ANATOMICAL_DIRECTIONS), doc="rules 'normal', 'extreme': an anatomical direction instead of `direction` (LPS: left +x, posterior +y, superior +z); empty = `direction`")
    markups: str = _f("", doc="rule 'markups': 3D Slicer markups file (.mrk.json, .fcsv) in the mesh's frame (LPS or RAS, as it says); points snap to the surface")
    markup_label: str = _f("", doc="rule 'markups': only the points with this label (or the list of this name); empty = every point of the file")
    snap: float = _f(20.0, lo=0.0, lo_open=True, doc="rule 'markups': farthest a point may lie from the outer surface, mm")
    label_map: str = _f("", doc="rule 'label': label map (.nii, .nii.gz, .nrrd, .seg.nrrd) in the mesh's frame; the surface vertices in, or one voxel from, the label")
    label: int = _f(0, lo=0, doc="rule 'label': voxel value of the label; 0 = the only non-zero value of the map")


@dataclass(frozen=True)
class SpringConfig(RegionConfig):
    """Elastic support: distributed linear springs tying a surface region to fixed surroundings.

    The stiffness per unit area k (N/mm^3 = MPa/mm) is lumped to the surface nodes by area;
    a layer of surrounding tissue of modulus E and thickness L resists about k = E / L
    (the default 0.0021 N/mm^3 is 0.021 MPa over 10 mm): a uniform pressure p then moves the
    surface by p / k.
    """

    normal_stiffness: float = _f(DEFAULT_SUPPORT_STIFFNESS, lo=0.0, lo_open=True, doc="stiffness per unit area normal to the surface, N/mm^3 (MPa/mm): surroundings of modulus E over a length L give about E / L (default 0.021 MPa / 10 mm)")
    tangential_stiffness: float = _f(DEFAULT_SUPPORT_STIFFNESS, lo=0.0, doc="stiffness per unit area along the surface, N/mm^3; equal to normal_stiffness = isotropic; 0 = the surface slides freely")
    lumping: str = _f("hrz", choices=("hrz", "row-sum"), doc="P2 nodal shares of the area: hrz = 1/19 per corner, 16/57 per mid-edge node; row-sum = none at corners (non-unique when compressed)")


@dataclass(frozen=True)
class GravityConfig:
    """Change of gravity between imaging and surgery: body force rho |g| (d_surgery - d_imaging)."""

    enabled: bool = _f(False, doc="add the change of gravity to every sample's loads")
    density: float = _f(1.0e-9, lo=0.0, lo_open=True, doc="tissue density in t/mm^3 (1000 kg/m^3 = 1 g/cm^3 = 1e-9 t/mm^3)")
    acceleration: float = _f(9810.0, lo=0.0, lo_open=True, doc="|g| in mm/s^2 (9.81 m/s^2 = 9810 mm/s^2)")
    imaging_direction: tuple[float, ...] = _f((0.0, 0.0, -1.0), doc="gravity's direction (LPS) in the reference image: default inferior; a supine CT/MR scan: posterior, [0, 1, 0]")
    surgery_direction: tuple[float, ...] = _f((0.0, 0.0, -1.0), doc="nominal direction of gravity during surgery (LPS; supine: [0, 1, 0], prone: [0, -1, 0])")
    cone_angle: float = _f(30.0, lo=0.0, hi=90.0, doc="each sample's surgery direction is drawn uniformly within this angle (degrees) of surgery_direction")


@dataclass(frozen=True)
class AccessConfig(RegionConfig):
    """Where an instrument can reach the surface (the surgical access: a craniotomy, a port, the
    exposed face): indentation patch centres are drawn among these surface vertices."""

    rule: str = _f("surface", choices=REGION_RULES[1:], doc="surface vertices an instrument reaches: surface = all; ids; tag; normal; distance; markups; extreme; label (as for the attached region)")


@dataclass(frozen=True)
class IndentationConfig:
    """An instrument pushing a small surface patch: prescribed displacement at a random site per sample."""

    enabled: bool = _f(False, doc="one indentation per sample")
    radius: float = _f(4.0, lo=0.0, lo_open=True, doc="patch radius, mm: the surface vertices within it (on the centre's side) move together")
    depth: tuple[float, ...] = _f((2.0, 6.0), lo=0.0, doc="[min, max] depth along the inward normal at the centre, mm, drawn uniformly")
    slide: tuple[float, ...] = _f((0.0, 2.0), lo=0.0, doc="[min, max] tangential slide, mm, drawn uniformly, in a uniformly drawn tangent direction")
    clearance: float = _f(8.0, lo=0.0, doc="patch centres lie at least this far (mm) from supported vertices (pins, attached region)")
    tool: str = _f("flat", choices=("flat", "rounded"), doc="flat = the patch moves together (a rigid punch, singular rim); rounded = a ball tip of tool_radius (Hertz profile)")
    tool_radius: float = _f(5.0, lo=0.0, lo_open=True, doc="tool rounded: radius of the instrument's rounded tip, mm")
    probability: float = _f(1.0, lo=0.0, hi=1.0, lo_open=True, doc="share of samples the instrument touches (drawn per sample from a stream of its own); the others have no indentation")
    access: AccessConfig = field(default_factory=AccessConfig, metadata={"doc": "the surgical access: the surface region where patch centres may lie (default the whole outer surface)"})


MATERIAL_REGION_RULES = ("cell_data", "distance")


@dataclass(frozen=True)
class MaterialRegionConfig:
    """One material region: neo-Hookean constants for a set of elements."""

    name: str = _f("region", doc="label")
    rule: str = _f("cell_data", choices=MATERIAL_REGION_RULES, doc="cell_data = the elements whose materials.cell_data value equals `value`; distance = the elements whose centroid lies within `distance` of `point`")
    value: int = _f(1, doc="rule 'cell_data': the region's value")
    point: tuple[float, ...] = _f((0.0, 0.0, 0.0), doc="rule 'distance': centre, mm")
    distance: float = _f(10.0, lo=0.0, lo_open=True, doc="rule 'distance': radius, mm")
    youngs_modulus: float = _f(0.021, lo=0.0, lo_open=True, doc="E in MPa")
    poisson_ratio: float = _f(0.45, lo=-1.0, hi=0.5, lo_open=True, hi_open=True, doc="nu")
    youngs_modulus_range: tuple[float, ...] = _f((), lo=0.0, lo_open=True, doc="[min, max] MPa: E is drawn uniformly once per data set; empty = youngs_modulus")
    poisson_ratio_range: tuple[float, ...] = _f((), lo=-1.0, hi=0.5, lo_open=True, hi_open=True, doc="[min, max]: nu drawn uniformly once per data set; empty = poisson_ratio")


@dataclass(frozen=True)
class MaterialRegionsConfig:
    """Per-element materials; elements in no region have the [material] section's constants."""

    cell_data: str = _f("", doc="name of the mesh file's integer cell-data array of region values (rule 'cell_data')")
    regions: tuple[MaterialRegionConfig, ...] = _f((), doc="the regions ([[scenario.materials.regions]] tables); a later region wins where two overlap")


#: Names of the parameters ``[scenario.uncertain]`` may draw (and ``measured`` may name).
UNCERTAIN_PARAMETERS = ("youngs_modulus", "poisson_ratio", "region_youngs_modulus", "density", "spring_normal",
                        "spring_tangential", "attached_margin")


@dataclass(frozen=True)
class UncertainConfig:
    """What is not known in the operating room, drawn anew for every sample (docs/uncertainty.md).

    Each key is a ``[min, max]`` range; empty = known (the nominal value, no draw). The model
    does not see these parameters unless ``measured`` names them (then they are model inputs).
    """

    youngs_modulus: tuple[float, ...] = _f((), lo=0.0, lo_open=True, doc="[min, max] factor on every element's E, drawn log-uniformly (e.g. [0.5, 2])")
    poisson_ratio: tuple[float, ...] = _f((), lo=0.0, hi=0.5, hi_open=True, doc="[min, max] Poisson's ratio of every element, drawn uniformly (e.g. [0.40, 0.49])")
    region_youngs_modulus: tuple[float, ...] = _f((), lo=0.0, lo_open=True, doc="[min, max] factor on each material region's E, drawn log-uniformly per region")
    density: tuple[float, ...] = _f((), lo=0.0, lo_open=True, doc="[min, max] factor on the tissue density (the gravity change), drawn uniformly")
    spring_normal: tuple[float, ...] = _f((), lo=0.0, lo_open=True, doc="[min, max] factor on the springs' normal stiffness, drawn log-uniformly (e.g. [0.25, 4])")
    spring_tangential: tuple[float, ...] = _f((), lo=0.0, lo_open=True, doc="[min, max] factor on the springs' tangential stiffness, drawn log-uniformly")
    attached_margin: tuple[float, ...] = _f((), doc="[min, max] mm the attached region grows (+) or shrinks (-) along the surface, drawn uniformly")
    measured: tuple[str, ...] = _f((), doc="parameters measured before surgery (e.g. 'youngs_modulus' by elastography): model inputs")
    nominal_share: float = _f(0.0, lo=0.0, hi=1.0, hi_open=True, doc="share of the samples drawn with every parameter at its nominal value (a prior that trusts the nominal guess; 0: every sample from the ranges)")
    arcsine: tuple[str, ...] = _f((), doc="drawn parameters whose range's ends are likelier: the arcsine law (Beta(1/2, 1/2)) over the range, log scale for factors")


#: The scenario loads an instrument can be (:class:`InstrumentConfig`): today the indentation.
INSTRUMENT_LOADS = ("indentation",)
#: OpenIGTLink device names hold at most 20 bytes (the header's char[20]).
DEVICE_NAME_BYTES = 20


@dataclass(frozen=True)
class InstrumentConfig:
    """A tracked instrument: a scenario load whose pose navigation streams, a model input
    (tissuecast.instruments, docs/scenarios.md)."""

    name: str = _f("retractor", doc="label; the model's inputs are <name>.tip_x ... <name>.contact")
    load: str = _f("indentation", choices=INSTRUMENT_LOADS, doc="the scenario load the instrument is: its pose in a sample follows from that load's draw")
    device: str = _f("RetractorTipToRef", doc="OpenIGTLink device (<= 20 characters) of the calibrated tip's TRANSFORM (tip -> tracker frame, e.g. RetractorTipToRef) for serve")


@dataclass(frozen=True)
class ScenarioConfig:
    """The clinical scenario: how the tissue is held and what loads it per sample.

    The defaults are the paper's: pinned vertices (``[markers]`` fixed_*) and LBO surface
    forces. Supports combine freely (pins, an attached region, an elastic support); loads are
    summed per sample (LBO forces, a change of gravity, one indentation).
    """

    name: str = _f("paper", doc="label shown in reports")
    pins: bool = _f(True, doc="hold the body by the pinned vertices of [markers] (fixed_count, fixed_rule, fixed_ids)")
    lbo_forces: bool = _f(True, doc="random LBO surface forces per sample (magnitude calibrated to forces.target_max_displacement)")
    attached: RegionConfig = field(default_factory=RegionConfig, metadata={"doc": "surface region fixed in all components (tissue attached to bone or muscle)"})
    springs: SpringConfig = field(default_factory=SpringConfig, metadata={"doc": "elastic support: springs tying a surface region to the surroundings"})
    gravity: GravityConfig = field(default_factory=GravityConfig, metadata={"doc": "change of gravity between imaging and surgery"})
    indentation: IndentationConfig = field(default_factory=IndentationConfig, metadata={"doc": "one instrument indentation per sample"})
    materials: MaterialRegionsConfig = field(default_factory=MaterialRegionsConfig, metadata={"doc": "per-element materials (e.g. a stiffer tumour)"})
    uncertain: UncertainConfig = field(default_factory=UncertainConfig, metadata={"doc": "parameters drawn per sample: what is unknown in the operating room"})
    instruments: tuple[InstrumentConfig, ...] = _f((), doc="tracked instruments ([[scenario.instruments]] tables): their poses are recorded per sample and are model inputs")


@dataclass(frozen=True)
class Config:
    """The whole run configuration. ``Config()`` reproduces the paper's set-up."""

    name: str = _f("tissuecast", doc="run name")
    output: str = _f("runs/tissuecast", doc="folder for everything the run writes")
    mesh: MeshConfig = field(default_factory=MeshConfig)
    markers: MarkerConfig = field(default_factory=MarkerConfig)
    material: MaterialConfig = field(default_factory=MaterialConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    forces: ForceConfig = field(default_factory=ForceConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    surrogate: SurrogateConfig = field(default_factory=SurrogateConfig)
    evaluate: EvaluateConfig = field(default_factory=EvaluateConfig)
    serve: ServeConfig = field(default_factory=ServeConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)


# ----------------------------------------------------------------- validation
def _range_text(meta: dict) -> str:
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo, hi = meta.get("lo"), meta.get("hi")
    left = "(" if meta.get("lo_open") else "["
    right = ")" if meta.get("hi_open") else "]"
    return f"in {left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"


def _check_scalar(key: str, value: Any, typ: Any, meta: dict) -> Any:
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key} must be a number, got {value!r} ({type(value).__name__})")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key} must be finite, got {value!r}")
    elif typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} must be an integer, got {value!r} ({type(value).__name__})")
    elif typ is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key} must be a string, got {value!r} ({type(value).__name__})")
    elif typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
    choices = meta.get("choices")
    if choices and value not in choices:
        raise ConfigError(f"{key} = {value!r} is not allowed; use {_range_text(meta)}")
    lo, hi = meta.get("lo"), meta.get("hi")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        bad = (lo is not None and (value < lo or (meta.get("lo_open") and value == lo))) or (
            hi is not None and (value > hi or (meta.get("hi_open") and value == hi))
        )
        if bad:
            raise ConfigError(f"{key} = {value!r} is out of range; allowed values are {_range_text(meta)}")
    return value


def _build(cls: type, data: Any, prefix: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"[{prefix.rstrip('.')}] must be a table, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown config key '{prefix}{unknown[0]}'; allowed keys{' in [' + prefix.rstrip('.') + ']' if prefix else ''}: "
            + ", ".join(sorted(fields))
        )
    kwargs = {}
    for name, value in data.items():
        key = prefix + name
        typ = hints[name]
        meta = dict(fields[name].metadata)
        if dataclasses.is_dataclass(typ):
            kwargs[name] = _build(typ, value, key + ".")
        elif typing.get_origin(typ) is tuple:
            item = typing.get_args(typ)[0]
            if not isinstance(value, (list, tuple)):
                raise ConfigError(f"{key} must be a list, got {value!r}")
            if dataclasses.is_dataclass(item):  # an array of tables, [[key]]
                kwargs[name] = tuple(_build(item, v, f"{key}[{i}].") for i, v in enumerate(value))
            else:
                kwargs[name] = tuple(_check_scalar(f"{key}[{i}]", v, item, meta) for i, v in enumerate(value))
        else:
            kwargs[name] = _check_scalar(key, value, typ, meta)
    obj = cls(**kwargs)
    _cross_checks(obj, prefix)
    return obj


def _cross_checks(obj: Any, prefix: str) -> None:
    if isinstance(obj, MeshConfig):
        _check_mesh_budget(obj, prefix)
    if isinstance(obj, DatasetConfig):
        if len(obj.split) != 3 or any(s < 0 for s in obj.split) or sum(obj.split) <= 0:
            raise ConfigError(f"{prefix}split must be three non-negative numbers (train, valid, test-1), got {list(obj.split)}")
        if obj.scheduler and not obj.scheduler.startswith(("tcp://", "tls://", "inproc://")):
            raise ConfigError(f"{prefix}scheduler must look like tcp://HOST:PORT, got {obj.scheduler!r}")
    if isinstance(obj, SurrogateConfig):
        if not obj.hidden or any(h < 1 for h in obj.hidden):
            raise ConfigError(f"{prefix}hidden must be a non-empty list of positive widths, got {list(obj.hidden)}")
        if obj.sensitivity_weight > 0 and obj.marker_dropout > 0:
            raise ConfigError(f"{prefix}sensitivity_weight > 0 needs marker_dropout = 0 (the sensitivities are those of "
                              "every marker); set one of them to 0")
    if isinstance(obj, ForceConfig):
        if not obj.betas or any(not 0.0 <= b <= 1.0 for b in obj.betas):
            raise ConfigError(f"{prefix}betas must be numbers in [0, 1], got {list(obj.betas)}")
        if obj.target_max_displacement < 0.1:
            raise ConfigError(f"{prefix}target_max_displacement = {obj.target_max_displacement!r} mm looks like metres; "
                              "lengths are in mm (e.g. 30 for 3 cm)")
    if isinstance(obj, MaterialConfig) and obj.check_range:
        _check_modulus(f"{prefix}youngs_modulus", obj.youngs_modulus, f"{prefix}check_range")
    if isinstance(obj, ServeConfig) and obj.tracker_to_client:
        from .frames import FrameError, check_transform

        try:
            check_transform(obj.tracker_to_client, f"{prefix}tracker_to_client")
        except FrameError as exc:
            raise ConfigError(f"{exc} (empty = no registration)") from exc
    if isinstance(obj, SolverConfig) and obj.min_increment > obj.initial_increment:
        raise ConfigError(f"{prefix}min_increment ({obj.min_increment}) must not exceed initial_increment ({obj.initial_increment})")
    if isinstance(obj, RegionConfig):
        _check_region(obj, prefix)
    if isinstance(obj, TargetConfig):
        _check_targets(obj, prefix)
    if isinstance(obj, GravityConfig):
        _check_vector(f"{prefix}imaging_direction", obj.imaging_direction)
        _check_vector(f"{prefix}surgery_direction", obj.surgery_direction)
        lo, hi = DENSITY_SPAN
        if not lo <= obj.density <= hi:
            raise ConfigError(
                f"{prefix}density = {obj.density!r} t/mm^3 is outside the range of tissues ({lo:g}..{hi:g}); density "
                "is in tonne per mm^3 (consistent with mm, N, s): 1000 kg/m^3 = 1 g/cm^3 = 1e-9 t/mm^3")
        if obj.acceleration < 100.0:
            raise ConfigError(f"{prefix}acceleration = {obj.acceleration!r} looks like m/s^2; it is in mm/s^2 "
                              "(9.81 m/s^2 = 9810 mm/s^2)")
    if isinstance(obj, IndentationConfig):
        for name in ("depth", "slide"):
            _check_range(f"{prefix}{name}", getattr(obj, name), required=True)
        if obj.radius < 0.1 or 0.0 < obj.depth[1] < 0.01:
            raise ConfigError(f"{prefix}radius = {obj.radius!r} mm and depth = {list(obj.depth)} mm look like metres; "
                              "lengths are in mm (e.g. radius 4, depth [2, 6])")
        if obj.depth[1] <= 0.0:
            raise ConfigError(f"{prefix}depth = {list(obj.depth)} never pushes; give [min, max] mm with max > 0")
        contact = (obj.tool_radius * obj.depth[1]) ** 0.5
        if obj.tool == "rounded" and contact > obj.radius:
            raise ConfigError(f"{prefix}radius = {obj.radius:g} mm is smaller than the rounded tool's largest contact "
                              f"radius sqrt(tool_radius x depth max) = {contact:.3g} mm; raise {prefix}radius to at "
                              f"least {contact:.3g} or lower {prefix}tool_radius")
    if isinstance(obj, UncertainConfig):
        _check_uncertain(obj, prefix)
    if isinstance(obj, MaterialRegionConfig):
        _check_vector(f"{prefix}point", obj.point, nonzero=False)
        _check_range(f"{prefix}youngs_modulus_range", obj.youngs_modulus_range)
        _check_range(f"{prefix}poisson_ratio_range", obj.poisson_ratio_range)
    if isinstance(obj, MaterialRegionsConfig):
        if any(r.rule == "cell_data" for r in obj.regions) and not obj.cell_data:
            raise ConfigError(f"{prefix}cell_data must name the mesh file's cell-data array of region values when a "
                              "region has rule = 'cell_data'")
        names = [r.name for r in obj.regions]
        if len(set(names)) != len(names):
            raise ConfigError(f"{prefix}regions repeat a name ({names}); give each region its own name")
    if isinstance(obj, Config):
        _check_scenario(obj)


def _check_region(obj: "RegionConfig", prefix: str) -> None:
    """A surface region's rule has the keys it needs, and no key of another rule."""
    _check_vector(f"{prefix}direction", obj.direction)
    _check_vector(f"{prefix}point", obj.point, nonzero=False)
    _check_place_rules(obj, prefix)
    if obj.rule == "ids" and not obj.ids:
        raise ConfigError(f"{prefix}rule = 'ids' needs {prefix}ids, a list of 0-based vertex ids")
    if obj.rule == "tag" and not obj.tag:
        raise ConfigError(f"{prefix}rule = 'tag' needs {prefix}tag, the name of a region of the mesh file "
                          "(`tissuecast mesh info FILE` lists them)")


def _check_place_rules(obj: "RegionConfig", prefix: str) -> None:
    """The keys of the region rules that carry over to other meshes (markups, extreme, label).

    Whether ``label_map`` names a label map is asked where label maps are known:
    :func:`tissuecast.scenario.regions.check_region_source`, at the edge.
    """
    if obj.toward and obj.rule not in ("normal", "extreme"):
        raise ConfigError(f"{prefix}toward applies to rules 'normal' and 'extreme', not {obj.rule!r}; remove it")
    for keys, rule in ((("markups", "markup_label"), "markups"), (("label_map", "label"), "label")):
        given = [k for k in keys if getattr(obj, k)]
        if given and obj.rule != rule:
            raise ConfigError(f"{prefix}{given[0]} applies to rule = '{rule}', not {obj.rule!r}; set "
                              f"{prefix}rule = '{rule}' or remove it")
    if obj.rule == "markups" and not obj.markups.lower().endswith((".mrk.json", ".fcsv")):
        raise ConfigError(f"{prefix}rule = 'markups' needs {prefix}markups, a 3D Slicer markups file (.mrk.json or "
                          f".fcsv), got {obj.markups!r}")


def _check_mesh_budget(obj: "MeshConfig", prefix: str) -> None:
    """``mesh.max_vertices``: 0 (no budget) or at least 4. Whether ``path`` names something
    that is meshed is asked where mesh files are known: :func:`tissuecast.mesh.source.check_mesh_source`."""
    if obj.max_vertices and obj.max_vertices < 4:
        raise ConfigError(f"{prefix}max_vertices = {obj.max_vertices} is too small; a tetrahedral mesh needs at "
                          "least 4 vertices (0 = no budget)")


def _check_uncertain(obj: "UncertainConfig", prefix: str) -> None:
    """Each range is [min, max]; ``measured`` and ``arcsine`` name drawn parameters."""
    for name in UNCERTAIN_PARAMETERS:
        _check_range(f"{prefix}{name}", getattr(obj, name))
    if obj.nominal_share and not any(getattr(obj, name) for name in UNCERTAIN_PARAMETERS):
        raise ConfigError(f"{prefix}nominal_share = {obj.nominal_share:g} with no parameter drawn; give a parameter a "
                          f"[min, max] range, or remove {prefix}nominal_share")
    for key in ("measured", "arcsine"):
        _check_drawn_names(obj, prefix, key)


def _check_drawn_names(obj: "UncertainConfig", prefix: str, key: str) -> None:
    """``obj.<key>`` (a list of parameter names) names parameters that ``obj`` draws."""
    names = getattr(obj, key)
    unknown = [m for m in names if m not in UNCERTAIN_PARAMETERS]
    if unknown:
        raise ConfigError(f"{prefix}{key} names {unknown}; choose among {list(UNCERTAIN_PARAMETERS)}")
    undrawn = [m for m in names if not getattr(obj, m)]
    if undrawn:
        raise ConfigError(f"{prefix}{key} names {undrawn}, which {prefix[:-1]} does not draw; give "
                          f"{prefix}{undrawn[0]} a [min, max] range, or leave it out of {prefix}{key}")


def _check_modulus(key: str, value: float, switch: str) -> None:
    """Refuse a Young's modulus outside :data:`SOFT_TISSUE_MODULUS_SPAN` (MPa), naming the
    likely unit slip and the switch that allows it."""
    lo, hi = SOFT_TISSUE_MODULUS_SPAN
    if lo <= value <= hi:
        return
    guess = ""
    for factor, unit in ((1e-3, "kPa"), (1e-6, "Pa"), (1e3, "GPa")):
        if lo <= value * factor <= hi:
            guess = f"; {value:g} {unit} would be {value * factor:g} MPa"
            break
    raise ConfigError(f"{key} = {value!r} MPa is outside soft tissue's range, {lo:g}-{hi:g} MPa (0.1 kPa to 1 MPa){guess}; "
                      f"moduli are in MPa (21 kPa = 0.021): fix the unit, or set {switch} = false for a stiffer material")


def _check_targets(t: "TargetConfig", prefix: str) -> None:
    """Each target rule has the keys it needs, and only those (a key of another rule is a slip).

    Whether ``path`` names a label map (rule 'label') is asked where label maps are known:
    :func:`tissuecast.evaluate.targets.check_target_source`, at the edge.
    """
    points_suffixes = (".csv", ".mrk.json", ".fcsv")
    if t.rule == "tag" and not t.tag:
        raise ConfigError(f"{prefix}rule = 'tag' needs {prefix}tag, the name of a region of the mesh file "
                          "(`tissuecast mesh info FILE` lists them)")
    if t.rule in ("label", "points") and not t.path:
        what = "a label map (.nii, .nii.gz, .nrrd, .seg.nrrd)" if t.rule == "label" else "a CSV or Slicer markups file"
        raise ConfigError(f"{prefix}rule = {t.rule!r} needs {prefix}path, {what}")
    if t.rule == "points" and not t.path.lower().endswith(points_suffixes):
        raise ConfigError(f"{prefix}path = {t.path!r}: rule 'points' reads " + ", ".join(points_suffixes))
    if t.segment and not t.path.lower().endswith(".seg.nrrd"):
        raise ConfigError(f"{prefix}segment names a segment of a 3D Slicer segmentation (.seg.nrrd); "
                          f"{prefix}path = {t.path!r} is not one: use {prefix}label")
    unused = [k for k, rules in (("tag", ("tag",)), ("path", ("label", "points")), ("label", ("label",)),
                                 ("segment", ("label",))) if getattr(t, k) and t.rule not in rules]
    if unused:
        raise ConfigError(f"{prefix}{unused[0]} does not apply to {prefix}rule = {t.rule!r}; remove it or change the rule")


def _check_vector(key: str, v: tuple, nonzero: bool = True) -> None:
    if len(v) != 3 or (nonzero and not any(x != 0.0 for x in v)):
        raise ConfigError(f"{key} must be 3 numbers (x, y, z){' not all zero' if nonzero else ''}, got {list(v)}")


def _check_range(key: str, v: tuple, required: bool = False) -> None:
    if (v or required) and (len(v) != 2 or v[0] > v[1]):
        raise ConfigError(f"{key} must be [min, max] with min <= max{'' if required else ' (or empty)'}, got {list(v)}")


def _check_scenario(cfg: "Config") -> None:
    """Checks of the scenario that need other sections (the material's modulus)."""
    sc = cfg.scenario
    if not (sc.pins or sc.attached.rule != "none" or sc.springs.rule != "none"):
        raise ConfigError("scenario has no support: the body could move freely; keep scenario.pins = true, or "
                          "set scenario.attached.rule or scenario.springs.rule")
    if not (sc.lbo_forces or sc.gravity.enabled or sc.indentation.enabled):
        raise ConfigError("scenario has no load: set scenario.lbo_forces = true, scenario.gravity.enabled or "
                          "scenario.indentation.enabled")
    _check_uncertain_needs(cfg)
    _check_instruments(sc)
    if cfg.material.check_range:
        for k, reg in enumerate(sc.materials.regions):
            key = f"scenario.materials.regions[{k}]"
            _check_modulus(f"{key}.youngs_modulus", reg.youngs_modulus, "material.check_range")
            for value in reg.youngs_modulus_range:
                _check_modulus(f"{key}.youngs_modulus_range", value, "material.check_range")
    if sc.springs.rule != "none":
        e = cfg.material.youngs_modulus
        lo, hi = SUPPORT_LENGTH_SPAN
        for name in ("normal_stiffness", "tangential_stiffness"):
            k = getattr(sc.springs, name)
            if k > 0.0 and not lo <= e / k <= hi:
                raise ConfigError(
                    f"scenario.springs.{name} = {k!r} N/mm^3 would be tissue of E = {e} MPa over {e / k:.3g} mm; "
                    "the stiffness is per unit area, in N/mm^3 (= MPa/mm): surroundings of modulus E over a "
                    f"length L give E / L, e.g. {DEFAULT_SUPPORT_STIFFNESS} for 0.021 MPa over 10 mm (a value in "
                    "N/m^3 is 1e9 times too large)")


_INSTRUMENT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


def _check_instruments(sc: "ScenarioConfig") -> None:
    """Each instrument has its own name and device, is a load the scenario has, and one load is
    one instrument."""
    loads = {"indentation": (sc.indentation.enabled, "scenario.indentation.enabled = true")}
    for k, inst in enumerate(sc.instruments):
        key = f"scenario.instruments[{k}]"
        if not _INSTRUMENT_NAME.fullmatch(inst.name):
            raise ConfigError(f"{key}.name = {inst.name!r} must start with a letter and hold only letters, digits "
                              "and '_' (it names the model's inputs, e.g. retractor.tip_x)")
        if not inst.device or not inst.device.isascii() or len(inst.device) > DEVICE_NAME_BYTES or " " in inst.device:
            raise ConfigError(f"{key}.device = {inst.device!r} must be 1-{DEVICE_NAME_BYTES} ASCII characters without "
                              "spaces (an OpenIGTLink device name, e.g. RetractorToReference)")
        enabled, how = loads[inst.load]
        if not enabled:
            raise ConfigError(f"{key}.load = {inst.load!r}, but the scenario has no {inst.load}; set {how}, or remove "
                              "the instrument")
    for what in ("name", "load", "device"):
        values = [getattr(i, what) for i in sc.instruments]
        if len(set(values)) != len(values):
            raise ConfigError(f"scenario.instruments repeat a {what} ({values}); each instrument has its own {what}"
                              + (" (one instrument per load)" if what == "load" else ""))


def _check_uncertain_needs(cfg: "Config") -> None:
    """An uncertain parameter needs what it varies (springs, gravity, an attached region,
    material regions), and E's factors must keep it in soft tissue's range."""
    sc, u = cfg.scenario, cfg.scenario.uncertain
    needs = {"spring_normal": (sc.springs.rule != "none", "scenario.springs.rule"),
             "spring_tangential": (sc.springs.rule != "none", "scenario.springs.rule"),
             "density": (sc.gravity.enabled, "scenario.gravity.enabled"),
             "attached_margin": (sc.attached.rule != "none", "scenario.attached.rule"),
             "region_youngs_modulus": (bool(sc.materials.regions), "scenario.materials.regions")}
    for name, (ok, key) in needs.items():
        if getattr(u, name) and not ok:
            raise ConfigError(f"scenario.uncertain.{name} varies something this scenario lacks; set {key}, or "
                              f"remove scenario.uncertain.{name}")
    if u.nominal_share:
        _check_nominal_share(u, cfg.material.poisson_ratio)
    lo, hi = SOFT_TISSUE_MODULUS_SPAN
    e = cfg.material.youngs_modulus
    if cfg.material.check_range and u.youngs_modulus and not lo <= min(u.youngs_modulus) * e <= max(u.youngs_modulus) * e <= hi:
        raise ConfigError(f"scenario.uncertain.youngs_modulus = {list(u.youngs_modulus)} are factors on material.youngs_modulus "
                          f"({e} MPa): they reach {min(u.youngs_modulus) * e:g}-{max(u.youngs_modulus) * e:g} MPa, outside soft "
                          f"tissue's {lo:g}-{hi:g} MPa; give factors (e.g. [0.5, 2]), or set material.check_range = false")


def _check_nominal_share(u: "UncertainConfig", nu: float) -> None:
    """A share of nominal samples needs every range to hold its nominal value (factor 1, margin
    0 mm, the material's nu), and no measured Poisson's ratio (a nominal sample records the
    elements' own, NaN, which a model input cannot take)."""
    nominal = {"youngs_modulus": 1.0, "region_youngs_modulus": 1.0, "density": 1.0, "spring_normal": 1.0,
               "spring_tangential": 1.0, "attached_margin": 0.0, "poisson_ratio": nu}
    for name, value in nominal.items():
        bounds = getattr(u, name)
        if bounds and not min(bounds) <= value <= max(bounds):
            raise ConfigError(f"scenario.uncertain.nominal_share = {u.nominal_share:g} draws samples at the nominal "
                              f"{name} ({value:g}), outside scenario.uncertain.{name} = {list(bounds)}; widen the range "
                              "to hold it, or remove scenario.uncertain.nominal_share")
    if "poisson_ratio" in u.measured:
        raise ConfigError("scenario.uncertain.nominal_share cannot go with a measured poisson_ratio (a nominal sample "
                          "keeps each element's own nu, which is no model input); remove one of the two")


def nothing_drawn() -> dict:
    """``[scenario.uncertain]`` overrides (for :func:`with_overrides`) that draw no parameter,
    measure none and keep no nominal share or arcsine law: every sample at the nominal parameters."""
    return {**{name: [] for name in UNCERTAIN_PARAMETERS}, "measured": [], "nominal_share": 0.0, "arcsine": []}


def config_from_dict(data: dict) -> Config:
    """Build a validated :class:`Config` from nested dicts (as read from TOML)."""
    return _build(Config, data, "")


def load_config(path: str | Path | None = None) -> Config:
    """Load a TOML config file; ``None`` gives the defaults (the paper's set-up).

    Relative paths inside the file (``mesh.path``, ``output``...) are kept as written and
    resolved by the caller against the current directory.
    """
    if path is None:
        return Config()
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {str(p)!r} does not exist; check the path (see `tissuecast config show`)")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {str(p)!r} is not valid TOML: {exc}") from exc
    return config_from_dict(data)


def config_to_dict(cfg: Any) -> dict:
    """Nested plain dict (tuples become lists) of a config or config section."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = config_to_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = [config_to_dict(x) if dataclasses.is_dataclass(x) else x for x in v]
        else:
            out[f.name] = v
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return str(v)


def config_to_toml(cfg: Config, comments: bool = True, *, changed_only: bool = False) -> str:
    """TOML text that :func:`load_config` reads back to an equal config.

    Nested sections become sub-tables (``[scenario.gravity]``), tuples of sections arrays of
    tables (``[[scenario.materials.regions]]``). With ``comments``, a value that differs from
    its default says so first (``# changed (default 0.021): ...``); ``changed_only`` writes
    those values alone (and the tables holding them), which read back to the same config.
    """
    lines: list[str] = []
    _toml_table(cfg, "", lines, comments, default=type(cfg)(), changed_only=changed_only)
    return "\n".join(lines).lstrip("\n") + "\n"


def _toml_table(obj: Any, name: str, lines: list, comments: bool, array: bool = False, *, default: Any = None,
                changed_only: bool = False) -> None:
    """Append ``obj``'s table (then its sub-tables) to ``lines``; ``default``: the same section
    at its defaults (None: no comparison, as for an array's tables, whose keys all count)."""
    own: list[str] = []
    later = []
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        d = getattr(default, f.name) if default is not None else None
        key = f"{name}.{f.name}" if name else f.name
        if dataclasses.is_dataclass(v):
            later.append((key, [v], False, d))
        elif isinstance(v, tuple) and v and dataclasses.is_dataclass(v[0]):
            if not (changed_only and default is not None and v == d):
                later.append((key, v, True, None))
        else:
            changed = default is not None and v != d
            if changed_only and default is not None and not changed:
                continue
            doc = f.metadata.get("doc", "")
            note = f"changed (default {_toml_value(d)}): {doc}" if changed else doc
            own.append(f"{f.name} = {_toml_value(v)}" + (f"  # {note}" if comments and note else ""))
    mark = len(lines)
    if name:
        lines += ["", f"[[{name}]]" if array else f"[{name}]"]
    lines += own
    for key, items, is_array, d in later:
        for item in items:
            _toml_table(item, key, lines, comments, is_array, default=None if is_array else d,
                        changed_only=changed_only)
    if changed_only and name and not array and not own and len(lines) == mark + 2:
        del lines[mark:]  # a table with nothing changed in it or below


def with_overrides(cfg: Config, **sections: dict) -> Config:
    """A copy of ``cfg`` with some section values replaced, validated like a file.

    Example: ``with_overrides(cfg, dataset={"n_samples": 100})``; nested sub-tables merge key
    by key (``scenario={"gravity": {"enabled": True}}`` keeps the other gravity keys).
    """
    data = config_to_dict(cfg)
    for sec, values in sections.items():
        if isinstance(values, dict):
            if sec not in data or not isinstance(data[sec], dict):
                raise ConfigError(f"unknown config section {sec!r}")
            _merge(data[sec], values)
        else:
            data[sec] = values
    return config_from_dict(data)


def _merge(into: dict, values: dict) -> None:
    """Update nested dicts key by key (a sub-table given in part keeps its other keys)."""
    for k, v in values.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v

