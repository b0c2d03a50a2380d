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
    "SurrogateConfig",
    "EvaluateConfig",
    "ServeConfig",
    "load_config",
    "config_from_dict",
    "config_to_dict",
    "config_to_toml",
    "with_overrides",
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


#: Fixed-vertex placement rules (see :func:`tissuecast.markers.select_fixed_vertices`).
FIXED_RULES = ("compact", "spread")


@dataclass(frozen=True)
class MarkerConfig:
    """Fiducial markers (revised k-center clustering) and fixed vertices."""

    count: int = _f(5, lo=1, hi=200, doc="number of fiducial markers n_d")
    start: int = _f(96, lo=0, doc="0-based start vertex v0 (paper: 97 1-based)")
    min_distance: float = _f(10.0, lo=0.0, doc="d_min in mm")
    ids: tuple[int, ...] = _f((), doc="user-given 0-based marker ids (overrides count/start)")
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


@dataclass(frozen=True)
class DatasetConfig:
    """Data-set generation."""

    store: str = _f("dataset.zarr", doc="path of the store")
    n_samples: int = _f(2000, lo=1, doc="number of LBO samples (train + valid + test-1)")
    split: tuple[float, ...] = _f((8.0, 1.0, 1.0), doc="train : valid : test-1 ratio")
    n_test2: int = _f(200, lo=0, doc="number of test-2 (LSC/beta) samples")
    seed: int = _f(0, lo=0, doc="base seed; per-sample seeds derive from it and the index")
    workers: int = _f(0, lo=0, hi=256, doc="local worker processes; 0 = automatic")
    scheduler: str = _f("", doc="Dask scheduler address tcp://HOST:PORT; empty = local")
    alpha: float = _f(0.0, lo=0.0, doc="LBO force magnitude alpha (N); 0 = calibrate to forces.target_max_displacement")
    calibration_samples: int = _f(24, lo=1, hi=1000, doc="pilot samples of the force-magnitude calibration")
    calibration_quantile: float = _f(0.9, lo=0.0, hi=1.0, doc="quantile of per-sample max displacement that meets the target")
    predictor: str = _f("reduced", choices=("reduced", "none"), doc="initial guess of each solve: reduced = a reduced-order model of the first predictor_samples solutions; none = zero")
    predictor_samples: int = _f(40, lo=2, hi=100000, doc="the first LBO samples (ids 0..n-1), solved from zero, whose solutions build the reduced model")
    predictor_tolerance: float = _f(0.01, lo=0.0, lo_open=True, hi=0.5, doc="ECSW hyper-reduction: relative error of the reduced internal forces")
    batch_size: int = _f(8, lo=1, hi=256, doc="samples a worker solves together once the reduced model exists (their solves with the shared reference factorisation gathered: Solver.solve_batch); 1 = one at a time; the last bits of a sample depend on its batch")
    time_budget: float = _f(10.0, lo=0.0, doc="a solver attempt running longer than this many times the running median of its phase's samples is stopped (the sample goes on with its cautious retries, else is recorded failed); 0 = no budget")
    time_budget_min: float = _f(60.0, lo=0.0, doc="the time budget is at least this many seconds (machine hiccups never stop a sample)")


#: Rules choosing the number of PCA components (see :class:`SurrogateConfig`).
PCA_RULES = ("validation", "paper")
#: Learning-rate schedules and PCA-weight scalings of the MLP's training (see :mod:`tissuecast.surrogate.mlp`).
SCHEDULES = ("onecycle", "cosine", "constant")
OUTPUT_SCALINGS = ("global", "component")


@dataclass(frozen=True)
class SurrogateConfig:
    """PCA + MLP surrogate and the ridge baseline."""

    n_components: int = _f(0, lo=0, doc="PCA components n_w; 0 = chosen by pca_rule")
    pca_rule: str = _f("validation", choices=PCA_RULES, doc="n_w when n_components = 0: 'validation' = lowest validation mean Offset_max of the trained model; 'paper' = the pca_max_error rule")
    pca_max_components: int = _f(64, lo=1, hi=1000, doc="validation rule: the network is trained on this many components, then truncated")
    pca_max_error: float = _f(1.0, lo=0.0, lo_open=True, doc="paper rule: max cross-validated vertex reconstruction error (mm)")
    pca_folds: int = _f(5, lo=2, hi=50, doc="paper rule: folds of the n_w cross-validation")
    hidden: tuple[int, ...] = _f((128, 64), doc="hidden layer widths")
    epochs: int = _f(2500, lo=1, doc="maximum training epochs")
    batch_size: int = _f(128, lo=1, doc="mini-batch size")
    learning_rate: float = _f(3e-3, lo=0.0, lo_open=True, hi=1.0, doc="Adam (peak) learning rate")
    patience: int = _f(250, lo=0, doc="early-stopping patience in epochs; 0 = off")
    noise_sigma: float = _f(0.0, lo=0.0, doc="marker noise augmentation (mm)")
    ridge_ratio: float = _f(1e-3, lo=0.0, doc="ridge a2/a1")
    seed: int = _f(0, lo=0, doc="training seed")
    schedule: str = _f("onecycle", choices=SCHEDULES, doc="learning-rate schedule")
    output_scaling: str = _f("global", choices=OUTPUT_SCALINGS, doc="PCA-weight scaling of the loss")
    weight_decay: float = _f(0.0, lo=0.0, doc="Adam weight decay")
    marker_dropout: float = _f(0.0, lo=0.0, hi=1.0, doc="share of training samples with one marker hidden; > 0 enables missing-marker input")
    ensemble: int = _f(1, lo=1, hi=64, doc="networks trained with different seeds (>= 2 gives uncertainty)")
    calibration_share: float = _f(0.125, lo=0.0, hi=0.5, hi_open=True, doc="share of the training split held out (seeded) to calibrate error bounds and the out-of-distribution alarm; 0 = neither")
    coverage: float = _f(0.9, lo=0.0, hi=1.0, lo_open=True, hi_open=True, doc="nominal coverage of the per-vertex error bounds: each vertex's error is below its bound with at least this probability")
    false_alarm_rate: float = _f(0.01, lo=0.0, hi=1.0, lo_open=True, hi_open=True, doc="share of in-distribution inputs allowed to raise the out-of-distribution alarm")


@dataclass(frozen=True)
class EvaluateConfig:
    """Evaluation and report."""

    output: str = _f("report", doc="report folder")
    renders: int = _f(3, lo=0, hi=100, doc="number of samples rendered in 3D")


#: How TRANSFORM marker input triggers predictions, and the frames a client may work in
#: (see :mod:`tissuecast.serve.session`, :mod:`tissuecast.serve.frames`).
TRANSFORM_MODES = ("frame", "each")
CLIENT_FRAMES = ("LPS", "RAS")


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
            kwargs[name] = tuple(_check_scalar(f"{key}[{i}]", v, item, meta) for i, v in enumerate(value))
        else:
            kwargs[name] = _check_scalar(key, value, typ, meta)
    obj = cls(**kwargs)
    _cross_checks(obj, prefix)
    return obj


def _cross_checks(obj: Any, prefix: str) -> None:
    if isinstance(obj, MeshConfig):
        from .mesh.labelmap import label_map_format

        kind = label_map_format(obj.path) if obj.path else None
        if (obj.label or obj.segment) and kind is None:
            raise ConfigError(f"{prefix}label and {prefix}segment apply only when {prefix}path names a label map "
                              f"(.nii, .nii.gz, .nrrd, .seg.nrrd), got path {obj.path!r}")
        if obj.segment and kind != "segmentation":
            raise ConfigError(f"{prefix}segment names a segment of a 3D Slicer segmentation (.seg.nrrd); "
                              f"{obj.path!r} is not one: use {prefix}label")
        if kind is not None and obj.units != "mm":
            raise ConfigError(f"{prefix}units applies to mesh files; a label map is read in its own physical units (mm), "
                              f"remove {prefix}units = {obj.units!r}")
    if isinstance(obj, DatasetConfig):
        if len(obj.split) != 3 or any(s < 0 for s in obj.split) or sum(obj.split) <= 0:
            raise ConfigError(f"{prefix}split must be three non-negative numbers (train, valid, test-1), got {list(obj.split)}")
        if obj.scheduler and not obj.scheduler.startswith(("tcp://", "tls://", "inproc://")):
            raise ConfigError(f"{prefix}scheduler must look like tcp://HOST:PORT, got {obj.scheduler!r}")
    if isinstance(obj, SurrogateConfig):
        if not obj.hidden or any(h < 1 for h in obj.hidden):
            raise ConfigError(f"{prefix}hidden must be a non-empty list of positive widths, got {list(obj.hidden)}")
    if isinstance(obj, ForceConfig):
        if not obj.betas or any(not 0.0 <= b <= 1.0 for b in obj.betas):
            raise ConfigError(f"{prefix}betas must be numbers in [0, 1], got {list(obj.betas)}")
    if isinstance(obj, ServeConfig) and obj.tracker_to_client:
        from .frames import FrameError, check_transform

        try:
            check_transform(obj.tracker_to_client, f"{prefix}tracker_to_client")
        except FrameError as exc:
            raise ConfigError(f"{exc} (empty = no registration)") from exc
    if isinstance(obj, SolverConfig) and obj.min_increment > obj.initial_increment:
        raise ConfigError(f"{prefix}min_increment ({obj.min_increment}) must not exceed initial_increment ({obj.initial_increment})")


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
            out[f.name] = list(v)
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


def config_to_toml(cfg: Config, comments: bool = True) -> str:
    """TOML text that :func:`load_config` reads back to an equal config."""
    lines: list[str] = []
    sections = []
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            sections.append((f.name, v))
        else:
            doc = f.metadata.get("doc", "")
            lines.append(f"{f.name} = {_toml_value(v)}" + (f"  # {doc}" if comments and doc else ""))
    for name, sec in sections:
        lines.append("")
        lines.append(f"[{name}]")
        for f in dataclasses.fields(sec):
            doc = f.metadata.get("doc", "")
            lines.append(f"{f.name} = {_toml_value(getattr(sec, f.name))}" + (f"  # {doc}" if comments and doc else ""))
    return "\n".join(lines) + "\n"


def with_overrides(cfg: Config, **sections: dict) -> Config:
    """A copy of ``cfg`` with some section values replaced, validated like a file.

    Example: ``with_overrides(cfg, dataset={"n_samples": 100})``.
    """
    data = config_to_dict(cfg)
    for sec, values in sections.items():
        if isinstance(values, dict):
            if sec not in data or not isinstance(data[sec], dict):
                raise ConfigError(f"unknown config section {sec!r}")
            data[sec].update(values)
        else:
            data[sec] = values
    return config_from_dict(data)

