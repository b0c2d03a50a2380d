"""Evaluate a DeformationModel on a data set: the MLP next to its baselines, per split and beta.

Every set shows the learned model (MLP), rigid registration from the same markers (what
navigation systems do today), the paper's ridge baseline, the PCA floor (the best any
prediction on the model's PCA basis can do), and the size of the deformations: peak
displacement and non-rigid part (:func:`tissuecast.registration.nonrigid_part`). Next to the
paper's Offset_mean / Offset_max over all vertices, every method gets the clinic's figures at
targets inside the tissue (:mod:`.targets`): TRE mean / p95 / max and the share of the
targets' displacement corrected (:func:`~.metrics.summarize_targets`).

All distances in mm, times in seconds. The inputs of every prediction are the benchmark
(FEM) displacements of the model's markers, as in the paper. Each method is the model's part
for it (``DeformationModel.predictor(method)``), called through the one predictor protocol
(:class:`~tissuecast.surrogate.field_predictor.FieldPredictor`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import rankdata

from ..errors import ModelError, RegistrationError
from .metrics import SetSummary, TargetSummary, summarize_offsets, summarize_targets, target_errors

__all__ = ["SetResult", "Evaluation", "evaluate_model", "method_fields", "auxiliary_values", "spearman_rows", "SPLITS",
           "METHODS",
           "PREDICTORS", "METHOD_LABELS"]

#: Samples predicted at once (bounds the memory to chunk x n x 3 floats per method).
CHUNK = 256
#: Single-sample timing: calls timed, distinct inputs cycled through, untimed warm-up calls.
TIMING_REPEATS = 2000
TIMING_INPUTS = 64
TIMING_WARMUP = 10

SPLITS = ("train", "valid", "test1", "test2")


def spearman_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Spearman rank correlation of each row pair of (B, n) arrays -> (B,)."""
    ra = rankdata(a, axis=1)
    rb = rankdata(b, axis=1)
    ra -= ra.mean(axis=1, keepdims=True)
    rb -= rb.mean(axis=1, keepdims=True)
    den = np.sqrt((ra**2).sum(axis=1) * (rb**2).sum(axis=1))
    return np.where(den > 0, (ra * rb).sum(axis=1) / np.where(den > 0, den, 1.0), 0.0)


#: Predictors compared on every set: the learned model, its baselines, and the PCA floor
#: (the projection of the true field on the model's PCA basis: what no prediction of this
#: model can beat).
METHODS = ("mlp", "rigid", "ridge", "pca_floor")
#: The methods that predict from the markers (the PCA floor needs the true field).
PREDICTORS = ("mlp", "rigid", "ridge")
METHOD_LABELS = {"mlp": "MLP", "rigid": "rigid registration", "ridge": "ridge", "pca_floor": "PCA floor"}


def method_fields(model, marker_displacements: np.ndarray, methods=PREDICTORS, auxiliary=None) -> dict:
    """The fields each predictor gives from the same marker displacements.

    The one place evaluation calls the model's predictors (``model.predictor(m)``, each a
    :class:`~tissuecast.surrogate.field_predictor.FieldPredictor`).

    Args:
        model: a fitted DeformationModel.
        marker_displacements: (B, n_d, 3) float, mm.
        methods: names among :data:`PREDICTORS`.
        auxiliary: (B, n_a) the samples' auxiliary inputs (instrument poses, measured
            parameters: ``model.auxiliary``) for a model that reads some; the baselines ignore them.

    Returns:
        ``{method: (B, n, 3) float64 mm}``; rigid registration is None when the markers cannot
        define one (fewer than 3, or collinear).
    """
    out = {}
    for m in methods:
        try:
            out[m] = np.asarray(model.predictor(m).predict(marker_displacements, auxiliary=auxiliary), dtype=np.float64)
        except RegistrationError:
            out[m] = None
    return out


@dataclass(eq=False)
class SetResult:
    """Per-sample results on one set of samples.

    Attributes:
        name: 'test1', 'test2', 'test2 beta=0.5', ...
        indices: (k,) sample indices in the data set.
        beta: (k,) LBO share of the force field (NaN for LBO samples).
        offsets: {method: (k, 2) float64 [Offset_mean, Offset_max] per sample, mm} for every
            method of :data:`METHODS`: 'mlp' the learned model, 'rigid' rigid registration
            from the markers (Kabsch), 'ridge' the paper's baseline, 'pca_floor' the true
            field's projection on the PCA basis.
        max_displacement: (k,) largest benchmark vertex displacement per sample, mm.
        nonrigid: (k,) non-rigid part per sample, mm: the largest vertex residual after the
            best rigid fit of the whole benchmark field.
        sigma_spearman: (k,) per-sample Spearman correlation of predicted uncertainty and
            true vertex error (ensembles only, else empty).
        sigma_max: (k,) largest per-vertex uncertainty per sample, mm (ensembles only).
        tre: {method: (k, 3) float64 [mean, p95, max] of the target errors per sample, mm}
            (NaN rows where a method could not predict).
        target_displacement: (k,) mean true displacement of the targets per sample, mm.
        refused: (k,) bool, the samples whose markers the model's input gate refuses
            (predicted all the same, the gate suspended: :meth:`DeformationModel.gate_suspended
            <tissuecast.surrogate.DeformationModel.gate_suspended>`); empty where not checked.
    """

    name: str
    indices: np.ndarray
    beta: np.ndarray
    offsets: dict
    max_displacement: np.ndarray
    nonrigid: np.ndarray
    sigma_spearman: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sigma_max: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tre: dict = field(default_factory=dict)
    target_displacement: np.ndarray = field(default_factory=lambda: np.zeros(0))
    refused: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    @property
    def refused_share(self) -> float:
        """Share of the set's samples the input gate refuses (NaN where not checked)."""
        return float(np.mean(self.refused)) if self.refused.size else float("nan")

    def summary(self, method: str) -> SetSummary:
        """Offsets of ``method`` (one of :data:`METHODS`) summarised over the set."""
        o = self.offsets[method]
        return summarize_offsets(o[:, 0], o[:, 1])

    def target_summary(self, method: str) -> TargetSummary | None:
        """Errors at the targets of ``method`` over the set (None without targets)."""
        if method not in self.tre:
            return None
        return summarize_targets(self.tre[method], self.target_displacement)

    @property
    def mlp(self) -> SetSummary:
        return self.summary("mlp")

    @property
    def ridge(self) -> SetSummary:
        return self.summary("ridge")

    @property
    def rigid(self) -> SetSummary:
        return self.summary("rigid")

    @property
    def pca_floor(self) -> SetSummary:
        return self.summary("pca_floor")

    @property
    def mlp_mean(self) -> np.ndarray:
        return self.offsets["mlp"][:, 0]

    @property
    def mlp_max(self) -> np.ndarray:
        return self.offsets["mlp"][:, 1]

    @property
    def gain_over_rigid(self) -> float:
        """Mean Offset_max of rigid registration divided by the MLP's (> 1: the model helps)."""
        return float(self.rigid.offset_max / max(self.mlp.offset_max, 1e-300))

    def subset(self, keep: np.ndarray, name: str) -> "SetResult":
        pick = lambda a: a[keep] if a.size else a  # noqa: E731
        return SetResult(name, self.indices[keep], self.beta[keep], {k: v[keep] for k, v in self.offsets.items()},
                         self.max_displacement[keep], self.nonrigid[keep], pick(self.sigma_spearman),
                         pick(self.sigma_max), {k: v[keep] for k, v in self.tre.items()},
                         pick(self.target_displacement), pick(self.refused))

    def deformation(self) -> dict:
        """Size of the deformations (mm): peak displacement and non-rigid part, median / p90 /
        max over the set, and the median share of the peak that is non-rigid."""
        share = self.nonrigid / np.maximum(self.max_displacement, 1e-300)
        return {"max_displacement_median": float(np.median(self.max_displacement)),
                "max_displacement_p90": float(np.percentile(self.max_displacement, 90)),
                "max_displacement_max": float(self.max_displacement.max()),
                "nonrigid_median": float(np.median(self.nonrigid)),
                "nonrigid_p90": float(np.percentile(self.nonrigid, 90)),
                "nonrigid_max": float(self.nonrigid.max()),
                "nonrigid_share_median": float(np.median(share))}

    def as_dict(self) -> dict:
        d = {"name": self.name, "count": int(self.indices.size)}
        d.update({m: self.summary(m).as_dict() for m in METHODS})
        d["gain_over_rigid"] = self.gain_over_rigid
        if self.tre:
            d["targets"] = {m: self.target_summary(m).as_dict() for m in self.tre}
        d["deformation"] = self.deformation()
        if self.refused.size:
            d["gate_refused"] = self.refused_share
        if self.sigma_spearman.size:
            d["uncertainty"] = {
                "vertex_spearman_mean": float(self.sigma_spearman.mean()),
                "sample_spearman_sigma_max_vs_offset_max": float(spearman_rows(self.sigma_max[None], self.mlp_max[None])[0])
                if self.indices.size > 1 else float("nan"),
            }
        return d


@dataclass(eq=False)
class Evaluation:
    """Everything the report shows about one model on one data set."""

    sets: dict
    by_beta: list
    predict_seconds: dict
    model_summary: dict
    targets: object = None

    def as_dict(self) -> dict:
        return {
            "sets": {k: v.as_dict() for k, v in self.sets.items()},
            "by_beta": [{"beta": b, **r.as_dict()} for b, r in self.by_beta],
            "predict_seconds": self.predict_seconds,
            "model": self.model_summary,
            "targets": self.targets.as_dict() if self.targets is not None else None,
        }

    def samples_table(self) -> list[dict]:
        """One row per evaluated sample (for CSV)."""
        rows = []
        for name, r in self.sets.items():
            for i in range(r.indices.size):
                row = {"set": name, "index": int(r.indices[i]), "beta": float(r.beta[i]),
                       "max_displacement": float(r.max_displacement[i]), "nonrigid_part": float(r.nonrigid[i])}
                for m in METHODS:
                    row[f"{m}_offset_mean"] = float(r.offsets[m][i, 0])
                    row[f"{m}_offset_max"] = float(r.offsets[m][i, 1])
                for m, t in r.tre.items():
                    row.update({f"{m}_tre_mean": float(t[i, 0]), f"{m}_tre_p95": float(t[i, 1]),
                                f"{m}_tre_max": float(t[i, 2])})
                if r.target_displacement.size:
                    row["target_displacement_mean"] = float(r.target_displacement[i])
                if r.sigma_spearman.size:
                    row["sigma_spearman"] = float(r.sigma_spearman[i])
                    row["sigma_max"] = float(r.sigma_max[i])
                rows.append(row)
        return rows


def _offsets(pred: np.ndarray, bench: np.ndarray) -> np.ndarray:
    """(B, 2) [Offset_mean, Offset_max] of predictions (B, n, 3) against the benchmark, mm."""
    e = np.linalg.norm(pred - bench, axis=2)
    return np.stack([e.mean(axis=1), e.max(axis=1)], axis=1)


def _chunk(model, bench: np.ndarray, targets, unc: bool, aux: np.ndarray | None = None) -> dict:
    """Per-sample figures of one chunk of true fields (B, n, 3) mm (auxiliary inputs ``aux``
    (B, n_a) or None): offsets and TRE of every method, peak displacement, non-rigid part, the
    input gate's refusals, and the ensemble's spread against the error."""
    from ..registration import nonrigid_part

    d = model.marker_displacements(bench)
    out = {"rf": np.array([v.refused for v in model.check_input(d)], dtype=bool)}
    fields = method_fields(model, d, auxiliary=aux)
    fields["pca_floor"] = model.pca_projection(bench)
    out.update({m: _offsets(f, bench) if f is not None else np.full((len(bench), 2), np.nan) for m, f in fields.items()})
    out["md"] = np.linalg.norm(bench, axis=2).max(axis=1)
    out["nr"] = nonrigid_part(model.mesh.points, bench)
    if targets is not None:
        true_t = targets.displacements(bench)
        out["td"] = np.linalg.norm(true_t, axis=2).mean(axis=1)
        nan = np.full((len(bench), 3), np.nan)
        for m, f in fields.items():
            out[f"tre_{m}"] = target_errors(targets.displacements(f), true_t) if f is not None else nan
    if unc:
        sigma = model.predict_with_uncertainty(d, auxiliary=aux)[1]
        out["ss"] = spearman_rows(sigma, np.linalg.norm(fields["mlp"] - bench, axis=2))
        out["sm"] = sigma.max(axis=1)
    return out


def _set_result(model, U: np.ndarray, idx: np.ndarray, beta: np.ndarray, name: str, targets=None,
                chunk: int = CHUNK, aux: np.ndarray | None = None) -> SetResult:
    parts: dict = {}
    for s in range(0, idx.size, chunk):
        rows = idx[s:s + chunk]
        for k, v in _chunk(model, np.asarray(U[rows], dtype=np.float64), targets, model.has_uncertainty,
                           None if aux is None else aux[rows]).items():
            parts.setdefault(k, []).append(v)
    cat = lambda k: np.concatenate(parts[k]) if k in parts else np.zeros(0)  # noqa: E731
    tre = {m: cat(f"tre_{m}") for m in METHODS} if targets is not None else {}
    return SetResult(name, idx, beta, {m: cat(m) for m in METHODS}, cat("md"), cat("nr"), cat("ss"), cat("sm"), tre,
                     cat("td"), cat("rf"))


def _timing(model, U, idx, repeats: int = TIMING_REPEATS, aux: np.ndarray | None = None) -> dict:
    """Single-sample prediction time (s): p50 and p99 over repeated calls (with the samples'
    auxiliary inputs ``aux`` (N, n_a), if any), the input gate on as in surgery: the inputs
    among the first ``TIMING_INPUTS`` of ``idx`` that the gate lets through (``"gate": True``;
    where it passes fewer than two, which would time one remembered frame, all of them with
    the gate suspended, ``"gate": False``)."""
    if idx.size == 0:
        return {}
    rows = idx[: min(TIMING_INPUTS, idx.size)]
    d = model.marker_displacements(np.asarray(U[rows], dtype=np.float64))
    passed = np.array([not v.refused for v in model.check_input(d)], dtype=bool)
    if passed.sum() < min(2, len(rows)):
        with model.gate_suspended():
            return {**_timing_calls(model, d, None if aux is None else aux[rows], repeats), "gate": False}
    return {**_timing_calls(model, d[passed], None if aux is None else aux[rows[passed]], repeats), "gate": True}


def _timing_calls(model, d: np.ndarray, aux: np.ndarray | None, repeats: int) -> dict:
    """p50 and p99 (s) of ``repeats`` single-sample ``model.predict`` calls cycling through inputs d (m, n_d, 3) mm."""
    a = [None] * len(d) if aux is None else aux
    for x, ax in zip(d[:TIMING_WARMUP], a):
        model.predict(x, auxiliary=ax)
    t = np.empty(repeats)
    for i in range(repeats):
        x, ax = d[i % len(d)], a[i % len(d)]
        t0 = time.perf_counter()
        model.predict(x, auxiliary=ax)
        t[i] = time.perf_counter() - t0
    return {"p50": float(np.percentile(t, 50)), "p99": float(np.percentile(t, 99)), "repeats": repeats}


def _scenario(model, dataset) -> dict | None:
    """The scenario the model was trained on (its record), else the data set's, else None."""
    return dict(model.scenario) if model.scenario else dataset.scenario


def evaluate_model(model, dataset, splits=("valid", "test1", "test2"), *, targets=None) -> Evaluation:
    """Offsets and target errors of the MLP, its baselines and the PCA floor on the converged
    samples of each split.

    Args:
        model: a fitted :class:`~tissuecast.surrogate.DeformationModel` on the data set's mesh.
        dataset: a :class:`tissuecast.dataset.Dataset` (or any object with ``displacements``,
            ``beta``, ``mesh``, ``scenario`` and ``select(split, status)``).
        splits: which splits to evaluate ('train', 'valid', 'test1', 'test2').
        targets: where TRE is measured (:class:`~.targets.Targets` on the model's mesh);
            default the interior rule (:func:`~.targets.interior_targets`, away from the
            vertices the supports hold).
    """
    from .targets import interior_targets

    if targets is None:
        targets = interior_targets(model.mesh, exclude=model.fixed)
    if model.n_vertices != dataset.mesh.n_vertices or model.mesh.fingerprint() != dataset.mesh.fingerprint():
        raise ModelError("the model was trained on another mesh than this data set's; evaluate it on its own data set")
    U = dataset.displacements
    beta = np.asarray(dataset.beta, dtype=np.float64)
    aux = auxiliary_values(model, dataset)
    sets, by_beta = {}, []
    with model.gate_suspended():  # simulated samples: the gate's verdicts are reported, not obeyed
        for name in splits:
            idx = np.asarray(dataset.select(name, status="done"), dtype=np.int64)
            if idx.size == 0:
                continue
            sets[name] = _set_result(model, U, idx, beta[idx], name, targets, aux=aux)
    if "test2" in sets:
        t2 = sets["test2"]
        for b in np.unique(t2.beta[np.isfinite(t2.beta)]):
            by_beta.append((float(b), t2.subset(t2.beta == b, f"test2 beta={b:g}")))
    timing_idx = np.asarray(dataset.select("test1", status="done"), dtype=np.int64)
    about = model.describe()
    summary = {**{k: about[k] for k in ("n_components", "markers", "ensemble", "hidden", "pca", "training")},
               "scenario": _scenario(model, dataset)}
    if model.has_nominal_expert and timing_idx.size:
        summary["nominal_expert"] = _routing(model, U, timing_idx, aux)
    seconds = _timing(model, U, timing_idx, aux=aux)
    return Evaluation(sets=sets, by_beta=by_beta, predict_seconds=seconds, model_summary=summary, targets=targets)


def _routing(model, U, idx: np.ndarray, aux: np.ndarray | None) -> dict:
    """How a model with a nominal expert routes the samples ``idx`` (test-1):
    :func:`~tissuecast.surrogate.experts.routing_figures` (mm, shares)."""
    from ..surrogate.experts import routing_figures

    return routing_figures(model, np.asarray(U[idx], dtype=np.float64), None if aux is None else aux[idx])


def auxiliary_values(model, dataset) -> np.ndarray | None:
    """(N, n_a) the data set's auxiliary inputs of a model or predictor (``model.auxiliary``:
    instrument poses, measured parameters), or None for a markers-only one."""
    if not model.auxiliary.width:
        return None
    from ..surrogate.data import dataset_auxiliary

    return dataset_auxiliary(dataset, model.auxiliary).values
