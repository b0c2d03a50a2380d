"""Parametric studies of the paper (section 13): hidden layers, number of markers, PCA size.

Each study trains on the data set's whole 'train' split (no share held out for error bounds
and alarms), checkpoints on 'valid' and reports test-1 accuracy (mm: Offset_mean / Offset_max,
and TRE at the config's ``[evaluate.targets]`` with the share of the targets' displacement
corrected) and training time (s); rows are plain dicts ready for CSV. Models read the auxiliary
inputs the config's scenario declares (tracked instruments, measured parameters); with tracked
instruments every row also has the markers-only fallback's figures (``mlp_markers_only_*``).
"""

from __future__ import annotations

import csv
import logging
import time
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import MarkerError, ModelError
from ..surrogate import DeformationModel, choose_n_components
from ..surrogate.auxiliary import AuxiliaryInputs
from ..surrogate.data import dataset_arrays, split_indices

__all__ = ["architecture_study", "marker_count_study", "pca_study", "write_rows", "study_markers", "study_targets"]

#: When a marker count does not fit at the configured spacing, the spacing shrinks by this
#: factor per try, at most this many times (0.75^30 ~ 2e-4 of it: any mesh then holds them).
SPACING_SHRINK = 0.75
SPACING_TRIES = 30
#: The studies' default grids: the paper's layer widths (every pair [n1, n2], trained this many
#: times each), its marker counts, and the largest n_w of the PCA study.
ARCHITECTURE_WIDTHS = (32, 64, 128, 256)
ARCHITECTURE_REPEATS = 3
MARKER_COUNTS = range(3, 21)
PCA_MAX_COMPONENTS = 100

log = logging.getLogger(__name__)


def write_rows(path, rows: list[dict]) -> Path:
    """Write study rows to CSV: a column for every key of any row, in order of first appearance (a
    row without a key leaves its cell empty: e.g. a model without a trust layer has no coverage)."""
    path = Path(path)
    if not rows:
        raise ModelError(f"no study rows to write to {str(path)!r}")
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for row in rows for k in row)))
        w.writeheader()
        w.writerows(rows)
    return path


def _arrays(dataset, config: Config):
    """The training arrays with the auxiliary inputs the config's scenario declares."""
    return dataset_arrays(dataset, AuxiliaryInputs.from_config(config.scenario))


def _test1(dataset, arrays=None):
    """``(test-1 fields (k, n, 3) mm, their auxiliary inputs (k, n_a) or None)``."""
    idx = split_indices(dataset, "test1")
    if idx.size == 0:
        raise ModelError("the data set has no converged test-1 samples to evaluate the study on")
    aux = None if arrays is None or arrays.auxiliary is None else arrays.auxiliary.values[idx]
    return np.asarray(dataset.displacements[idx], dtype=np.float64), aux


def _scores(model: DeformationModel, bench: np.ndarray, targets, aux: np.ndarray | None = None) -> dict:
    """Test-1 figures of a model and its baselines (mm): MLP, rigid registration from the same
    markers, ridge, and the PCA floor of its basis; TRE at the targets and the share of the
    targets' displacement corrected (mean over samples) of the MLP and rigid registration; with
    tracked instruments (``aux``: the samples' auxiliary inputs), the markers-only fallback's
    Offset_mean and Offset_max."""
    from .evaluation import method_fields
    from .metrics import summarize_targets, target_errors

    d = model.marker_displacements(bench)
    fields = method_fields(model, d, auxiliary=aux)
    err = {m: np.linalg.norm(f - bench, axis=2) if f is not None else np.full(bench.shape[:2], np.nan)
           for m, f in fields.items()}
    ef = np.linalg.norm(model.pca_projection(bench) - bench, axis=2)
    row = {"mlp_offset_mean": float(err["mlp"].mean()), "mlp_offset_max": float(err["mlp"].max(axis=1).mean()),
           "mlp_share_below_1mm": float(np.mean(err["mlp"].max(axis=1) < 1.0)),
           "rigid_offset_max": float(err["rigid"].max(axis=1).mean()),
           "ridge_offset_mean": float(err["ridge"].mean()), "ridge_offset_max": float(err["ridge"].max(axis=1).mean()),
           "pca_floor_offset_max": float(ef.max(axis=1).mean())}
    if model.fallback_ is not None:
        kept = None if aux is None else aux[:, len(model.auxiliary.instrument_columns):]
        e = np.linalg.norm(model.fallback_.predict(d, auxiliary=kept if model.fallback_.auxiliary.width else None)
                           - bench, axis=2)
        row.update(mlp_markers_only_offset_mean=float(e.mean()), mlp_markers_only_offset_max=float(e.max(axis=1).mean()),
                   mlp_markers_only_share_below_1mm=float(np.mean(e.max(axis=1) < 1.0)))
    true_t = targets.displacements(bench)
    moved = np.linalg.norm(true_t, axis=2).mean(axis=1)
    for m in ("mlp", "rigid", "ridge"):
        f = fields[m]
        tre = target_errors(targets.displacements(f), true_t) if f is not None else np.full((len(bench), 3), np.nan)
        summary = summarize_targets(tre, moved)
        row[f"{m}_tre_mean"] = summary.tre_mean
        if m != "ridge":
            row[f"{m}_share_corrected"] = summary.share_corrected_mean
    return row


def study_targets(dataset, config: Config, fixed=()):
    """The targets of the config's ``[evaluate.targets]`` on the data set's mesh (TRE in every row)."""
    from .targets import targets_from_config

    return targets_from_config(config.evaluate.targets, dataset.mesh, mesh_path=config.mesh.path, exclude=fixed)


def _n_components(arrays, config: Config) -> int:
    """n_w shared by every fit of a study: the configured one, the paper rule's choice (computed
    once), or 0 when each fit chooses its own by validation."""
    sc = config.surrogate
    if sc.n_components:
        return sc.n_components
    if sc.pca_rule != "paper":
        return 0
    U = arrays.displacements[arrays.train_idx]
    return choose_n_components(U, sc.pca_max_error, sc.pca_folds, seed=sc.seed)[0]


def architecture_study(dataset, config: Config, *, widths=ARCHITECTURE_WIDTHS, repeats: int = ARCHITECTURE_REPEATS,
                       on_row=None) -> list[dict]:
    """Two hidden layers [n1, n2] over ``widths``^2, ``repeats`` seeds each.

    Args:
        dataset: a data set with train/valid/test1 samples.
        config: the run configuration (surrogate section used; ``hidden`` and ``seed`` varied).
        widths: layer widths to combine.
        repeats: trainings per architecture (seeds ``seed + r``).
        on_row: optional callback receiving each row when ready (progress).

    Returns:
        Rows: n1, n2, repeat, seed, test-1 offsets (MLP, ridge), best epoch, seconds.
    """
    arrays = _arrays(dataset, config)
    bench, aux = _test1(dataset, arrays)
    targets = study_targets(dataset, config, arrays.fixed)
    n_w = _n_components(arrays, config)
    rows = []
    for n1 in widths:
        for n2 in widths:
            for r in range(repeats):
                seed = config.surrogate.seed + r
                m = DeformationModel(config, hidden=(int(n1), int(n2)), seed=seed, n_components=n_w, ensemble=1,
                                     calibration="none")
                t0 = time.perf_counter()
                m.fit(arrays.displacements, arrays.markers, mesh=arrays.mesh, fixed=arrays.fixed,
                      train_idx=arrays.train_idx, valid_idx=arrays.valid_idx, auxiliary=arrays.auxiliary)
                row = {"n1": int(n1), "n2": int(n2), "repeat": r, "seed": seed, "n_components": m.n_components,
                       **_scores(m, bench, targets, aux), "best_epoch": m.summaries_[0].best_epoch,
                       "epochs_run": m.summaries_[0].epochs_run, "seconds": time.perf_counter() - t0}
                rows.append(row)
                if on_row:
                    on_row(row)
    return rows


def study_markers(mesh, count: int, config: Config, exclude=None) -> tuple[np.ndarray, float]:
    """``count`` markers by revised k-center from the config's start vertex, never on the
    vertices ``exclude`` (0-based; the data set's fixed vertices: what the supports hold moves
    not at all); d_min is reduced (by :data:`SPACING_SHRINK` per try) when the mesh cannot hold
    that many at the configured spacing.

    Returns:
        ``(markers (count,) int64, d_min used in mm)``.
    """
    from ..markers import select_markers

    mc = config.markers
    d_min = mc.min_distance
    for _ in range(SPACING_TRIES):
        try:
            return select_markers(mesh, count=count, start=mc.start, min_distance=d_min, exclude=exclude), d_min
        except MarkerError:
            d_min *= SPACING_SHRINK
    raise ModelError(f"cannot place {count} markers on this mesh even with d_min = {d_min:.3g} mm")


def marker_count_study(dataset, config: Config, *, counts=MARKER_COUNTS, on_row=None) -> list[dict]:
    """Test-1 accuracy versus the number of markers n_d (markers re-chosen by revised k-center).

    The data set's fields hold every vertex, so no new simulation is needed. The markers for
    n_d are the first n_d centers of one clustering run (the paper's rule), so sets are nested.
    With the validation rule each n_d gets its own n_w (more markers can use more
    components); every row shows the rigid baseline and the PCA floor of its basis.
    """
    arrays = _arrays(dataset, config)
    bench, aux = _test1(dataset, arrays)
    targets = study_targets(dataset, config, arrays.fixed)
    n_w = _n_components(arrays, config)
    all_markers, d_min = study_markers(arrays.mesh, max(counts), config, exclude=arrays.fixed)
    rows = []
    for k in counts:
        m = DeformationModel(config, n_components=n_w, ensemble=1, calibration="none")
        t0 = time.perf_counter()
        m.fit(arrays.displacements, all_markers[:k], mesh=arrays.mesh, fixed=arrays.fixed,
              train_idx=arrays.train_idx, valid_idx=arrays.valid_idx, auxiliary=arrays.auxiliary)
        row = {"n_markers": int(k), "d_min": d_min, "n_components": m.n_components, **_scores(m, bench, targets, aux),
               "seconds": time.perf_counter() - t0, "markers": " ".join(map(str, all_markers[:k].tolist()))}
        rows.append(row)
        if on_row:
            on_row(row)
    return rows


def pca_study(dataset, config: Config, *, max_components: int = PCA_MAX_COMPONENTS) -> list[dict]:
    """Cross-validated PCA reconstruction error versus n_w on the training split."""
    arrays = dataset_arrays(dataset)
    sc = config.surrogate
    _, curve = choose_n_components(arrays.displacements[arrays.train_idx], sc.pca_max_error, sc.pca_folds,
                                   max_components=max_components, seed=sc.seed, full_curve=True)
    return [{"n_components": int(n), "max_error": float(a), "mean_max_error": float(b), "mean_error": float(c),
             "chosen": int(n == curve.chosen)}
            for n, a, b, c in zip(curve.n_components, curve.max_error, curve.mean_max_error, curve.mean_error)]
