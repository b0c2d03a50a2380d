"""A nominal expert beside an uncertainty-trained model, and the gate that routes between them.

A model trained with the scenario's parameters drawn (``[scenario.uncertain]``) pays for its
robustness at the nominal parameters: it regresses a much wider family of fields
(docs/uncertainty.md). A model trained at the nominal parameters alone (the *nominal expert*,
on the same mesh, markers and instruments) is about twice as accurate there and fails where a
parameter is far off (the attached region's extent above all). :class:`NominalExpertRouter`
keeps both and sends each sample's field to one of them by an :class:`ExpertGate`: a logistic
regression of how far the inputs lie from each model's training inputs (the input distance of
each model's alarm, on a log scale), fitted on held-out samples of both families (the
validation splits of the uncertain and the nominal store) with the label "the nominal expert's
largest vertex error is the smaller". The gate sends a sample to the nominal expert when that
probability is above one half, or to the uncertainty-trained model where a distance is not
finite. It reads the inputs only, so a sample is routed before any field is computed, and only
the field it is routed to (and the uncertainty-trained model's, whose bounds the routed ones
scale) is decoded; the alarm can follow the field as with one model. (A gate that also read
both alarms' other scores and how far the two fields lie apart routed no better: measured in
docs/uncertainty.md.)

The alarm is always the uncertainty-trained model's: it was calibrated on the whole range of
parameters, the nominal expert's only at the nominal ones. The error bounds are calibrated per
route (Mondrian conformal, :class:`RouteCalibration`): on the held-out samples drawn as the
uncertainty-trained model's training data were (the uncertain store's validation split), each
routed by a gate fitted without it (:func:`out_of_fold_routes`, :data:`ROUTE_FOLDS` folds), the routed field's
vertex errors over the uncertainty-trained model's bound give one set of conformal scores for
the samples the gate sends to the expert and one for the rest. A sample's bound is its route's
quantile times that bound, so the bounds hold at their coverage on each route under the
distribution the model's own bounds hold under; before, the expert's route had no bound of its
own. (Calibrating on the nominal store's samples too makes the expert's route look easier than
it is off the nominal parameters: measured in docs/uncertainty.md.) Where a route has too few
samples for the coverage asked, and for a sample whose instrument is not tracked (the model's
fallback answers: the scores are of the model with its instrument), the model's bound is kept.
A pair saved without route scores keeps that model's bounds everywhere. A sample with untracked
markers is predicted by the uncertainty-trained model alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ModelError, require
from .conformal import VertexConformal
from .fallback import InstrumentFallback
from .field_predictor import FieldPredictor
from .trust import TrustedPrediction
from .trusted import TrustedPredictor

__all__ = ["ExpertGate", "NominalExpertRouter", "RouteCalibration", "RoutedNetworks", "GATE_FEATURES", "gate_features",
           "check_expert", "routing_figures", "out_of_fold_routes", "gate_description", "routed_networks", "ROUTE_FOLDS"]

#: The gate's inputs, in order: each model's input distance (:attr:`~.trust.Alarm.distance`).
GATE_FEATURES = ("nominal_distance", "uncertain_distance")
#: Distances are read on a log scale; smaller values count as this (an input on a training input).
FEATURE_FLOOR = 1e-6
#: L2 penalty of the gate's logistic regression, on standardised features (the intercept is free).
GATE_PENALTY = 1.0
#: Newton iterations of the logistic fit at most (it converges in about ten).
GATE_ITERATIONS = 100
#: Folds of the out-of-fold routes the bounds are calibrated on (:func:`out_of_fold_routes`).
ROUTE_FOLDS = 5


def gate_features(nominal: FieldPredictor, uncertain: FieldPredictor, d: np.ndarray, a: np.ndarray | None) -> np.ndarray:
    """The gate's inputs (B, len(GATE_FEATURES)) float64 of checked marker displacements d
    (B, 3 n_d) mm and auxiliary inputs a (B, n_a) or None: both trusted predictors' input
    distances (``input_distance``), on a log scale (NaN where a distance is)."""
    X = np.stack([_input_distance(p, d, a) for p in (nominal, uncertain)], axis=1)
    with np.errstate(invalid="ignore"):
        return np.log(np.where(np.isnan(X), np.nan, np.maximum(X, FEATURE_FLOOR)))


def _input_distance(predictor: FieldPredictor, d: np.ndarray, a: np.ndarray | None) -> np.ndarray:
    """``predictor.input_distance`` of inputs the router has checked already: a trusted network
    (and the primary of an instrument fallback, the tracked frames) reads them through its trust
    layer directly, without checking them again in every nested predictor (what most of the
    gate's time went to: docs/serving.md); any other predictor, and the frames whose instrument
    is lost, through its ``input_distance``."""
    if isinstance(predictor, InstrumentFallback) and a is not None:
        lost = predictor.routes(a)
        if not lost.any():
            return _input_distance(predictor.primary, d, a)
        out = np.empty(len(d))
        if (~lost).any():
            out[~lost] = _input_distance(predictor.primary, d[~lost], a[~lost])
        if lost.any():
            out[lost] = predictor.input_distance(d[lost], auxiliary=a[lost])
        return out
    if isinstance(predictor, TrustedPredictor):
        return predictor.layer.ood.distance(predictor.layer.inputs(d, a, len(d)))
    return predictor.input_distance(d, auxiliary=a)


@dataclass(frozen=True, eq=False)
class ExpertGate:
    """A fitted gate: the probability that the nominal expert's field is the better one.

    Attributes:
        mean, scale: (f,) the standardisation of the features (:data:`GATE_FEATURES`).
        weights: (f,) logistic coefficients on the standardised features; ``bias`` the intercept.
        samples: how many held-out samples it was fitted on; ``nominal_better`` the share of them
            on which the nominal expert's largest vertex error was the smaller.
    """

    mean: np.ndarray
    scale: np.ndarray
    weights: np.ndarray
    bias: float
    samples: int
    nominal_better: float

    @classmethod
    def fit(cls, features: np.ndarray, nominal_better: np.ndarray, *, penalty: float = GATE_PENALTY) -> "ExpertGate":
        """L2-penalised logistic regression (Newton's method) of the labels ``nominal_better``
        (B,) bool on ``features`` (B, f) (:func:`gate_features`).

        Raises:
            ModelError: a feature is not finite, or every label is the same (nothing to route).
        """
        X = np.asarray(features, dtype=np.float64)
        y = np.asarray(nominal_better, dtype=bool)
        if X.ndim != 2 or X.shape[1] != len(GATE_FEATURES) or len(X) != len(y):
            raise ModelError(f"the gate needs features (B, {len(GATE_FEATURES)}) and B labels; got {X.shape} and {y.shape}")
        if not np.isfinite(X).all():
            raise ModelError("a model's input distance is not finite on the gate's samples: fit the gate on finite "
                             "fields (a store's converged samples)")
        if y.all() or not y.any():
            who = "the nominal expert" if y.all() else "the uncertainty-trained model"
            raise ModelError(f"{who} is the better one on all {len(y)} samples: there is nothing to route; use that "
                             "model alone, or fit the gate on samples drawn from the whole range of parameters")
        mean, scale = X.mean(axis=0), X.std(axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        Z = np.hstack([(X - mean) / scale, np.ones((len(X), 1))])
        reg = np.full(Z.shape[1], float(penalty))
        reg[-1] = 0.0
        w = np.zeros(Z.shape[1])
        t = y.astype(np.float64)
        for _ in range(GATE_ITERATIONS):
            p = _sigmoid(Z @ w)
            grad = Z.T @ (p - t) + reg * w
            hess = (Z * (p * (1.0 - p))[:, None]).T @ Z + np.diag(reg + 1e-12)
            step = np.linalg.solve(hess, grad)
            w -= step
            if np.abs(step).max() < 1e-12:
                break
        return cls(mean, scale, w[:-1].copy(), float(w[-1]), int(len(y)), float(y.mean()))

    def probability(self, features: np.ndarray) -> np.ndarray:
        """(B,) probability that the nominal expert is the better one (NaN where a feature is)."""
        Z = (np.asarray(features, dtype=np.float64) - self.mean) / self.scale
        return _sigmoid(Z @ self.weights + self.bias)

    def to_nominal(self, features: np.ndarray) -> np.ndarray:
        """(B,) bool: the samples whose field the nominal expert gives (probability above one
        half; never where a feature is not finite)."""
        X = np.asarray(features, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return np.isfinite(X).all(axis=1) & (self.probability(X) > 0.5)

    def as_dict(self) -> dict:
        """JSON-able form (``model.json``'s ``nominal_expert.gate``)."""
        return {"features": list(GATE_FEATURES), "mean": self.mean.tolist(), "scale": self.scale.tolist(),
                "weights": self.weights.tolist(), "bias": self.bias, "samples": self.samples,
                "nominal_better": self.nominal_better}

    @classmethod
    def from_dict(cls, doc: dict) -> "ExpertGate":
        """Read :meth:`as_dict`'s form.

        Raises:
            ModelError: other features than this version's gate reads.
        """
        if list(doc.get("features", [])) != list(GATE_FEATURES):
            raise ModelError(f"the model's expert gate reads {doc.get('features')}, this version {list(GATE_FEATURES)}; "
                             "fit the gate again (`tissuecast experts`)")
        arrays = [np.asarray(doc[k], dtype=np.float64) for k in ("mean", "scale", "weights")]
        if any(a.shape != (len(GATE_FEATURES),) for a in arrays):
            raise ModelError("the model's expert gate is damaged: its arrays do not match its features")
        return cls(*arrays, float(doc["bias"]), int(doc["samples"]), float(doc["nominal_better"]))


@dataclass(frozen=True, eq=False)
class RoutedNetworks:
    """A pair's two networks and its gate as one graph: what the torch and ONNX exports of a model
    with a nominal expert compute (:func:`routed_networks`).

    The graph computes both input distances, the gate's decision as :meth:`ExpertGate.to_nominal`
    takes it, both networks' fields, and gives each sample the field it is routed to: the nominal
    expert's where the gate says so and every marker is tracked (``present`` all 1, for a masked
    network), else the uncertainty-trained network's. In float32: a sample whose gate logit lies
    within round-off of 0 can take the other route than the float64 model.

    Attributes:
        uncertain, nominal: the two learned predictors (:class:`~.network_predictor.NetworkPredictor`).
        uncertain_distance, nominal_distance: their trust layers' :class:`~.ood.InputDistance`.
        gate: the fitted :class:`ExpertGate`.
    """

    uncertain: object
    nominal: object
    uncertain_distance: object
    nominal_distance: object
    gate: ExpertGate

    @property
    def n_markers(self) -> int:
        return self.uncertain.n_markers

    @property
    def markers(self) -> np.ndarray:
        return self.uncertain.markers

    @property
    def mesh(self):
        return self.uncertain.mesh

    @property
    def auxiliary(self):
        return self.uncertain.auxiliary

    @property
    def supports_missing_markers(self) -> bool:
        return bool(self.uncertain.supports_missing_markers)

    def torch_module(self):
        """The routed graph as a torch module (float32), called as the networks' modules are
        (:func:`~.network.torch_network`): ``markers`` (B, n_d, 3) mm [, ``auxiliary`` (B, n_a)]
        [, ``present`` (B, n_d) 1/0 for a masked network] -> (B, n, 3) mm."""
        torch = require("torch", "learn", "the torch/ONNX graph of a model with a nominal expert")
        n_aux = self.auxiliary.width
        nominal_masked = bool(self.nominal.supports_missing_markers)
        gate = self.gate
        parts = {"uncertain": self.uncertain.torch_module(), "nominal": self.nominal.torch_module(),
                 "uncertain_distance": self.uncertain_distance.torch_module(),
                 "nominal_distance": self.nominal_distance.torch_module()}

        class RoutedNetwork(torch.nn.Module):
            def __init__(self):
                super().__init__()
                for name, module in parts.items():
                    self.add_module(name, module)
                for name, v in (("gate_mean", gate.mean), ("gate_scale", gate.scale), ("gate_weights", gate.weights)):
                    self.register_buffer(name, torch.as_tensor(v, dtype=torch.float32))
                self.gate_bias = float(gate.bias)

            def to_nominal(self, markers, *extra):
                """(B,) bool: the samples the gate routes to the nominal expert."""
                x = markers.reshape(markers.shape[0], -1)
                if n_aux:
                    x = torch.cat([x, extra[0]], dim=1)
                f = torch.stack([self.nominal_distance(x), self.uncertain_distance(x)], dim=1)  # GATE_FEATURES' order
                f = torch.log(torch.clamp(f, min=FEATURE_FLOOR))
                logit = ((f - self.gate_mean) / self.gate_scale) @ self.gate_weights + self.gate_bias
                route = torch.isfinite(f).all(dim=1) & (logit > 0)
                if len(extra) > (1 if n_aux else 0):  # present: an untracked marker keeps the uncertain network
                    route = route & (extra[-1].min(dim=1).values > 0.5)
                return route

            def forward(self, markers, *extra):
                route = self.to_nominal(markers, *extra)
                theirs = extra if nominal_masked else extra[:1 if n_aux else 0]
                return torch.where(route[:, None, None], self.nominal(markers, *theirs), self.uncertain(markers, *extra))

        return RoutedNetwork().eval()


def routed_networks(state, fallback: bool = False) -> RoutedNetworks:
    """The :class:`RoutedNetworks` of a pair's :class:`~.state.ModelState` (``state.expert`` set):
    of the two networks with their instruments, or (``fallback``) of the two fallbacks without
    them (the frames whose instrument is not tracked).

    Raises:
        ModelError: the state has no nominal expert, a trust layer is missing, or ``fallback``
            for a pair without fallbacks.
    """
    expert = state.expert
    if expert is None:
        raise ModelError("this model has no nominal expert: its graph is its network's")
    if fallback:
        if state.fallback is None or expert.fallback is None:
            raise ModelError("this model has no fallback: it reads no tracked instrument")
        nets, layers = (state.fallback, expert.fallback), (state.fallback_trust, expert.fallback_trust)
    else:
        nets, layers = (state.network, expert.network), (state.trust, expert.trust)
    if layers[0] is None or layers[1] is None:
        raise ModelError("a model with a nominal expert needs both trust layers (the gate reads their input distances); "
                         "make the pair again with `tissuecast experts`")
    return RoutedNetworks(nets[0], nets[1], layers[0].ood.distance, layers[1].ood.distance, state.expert_gate)


def out_of_fold_routes(features: np.ndarray, nominal_better: np.ndarray, folds: int = ROUTE_FOLDS) -> np.ndarray:
    """(B,) bool: where a gate fitted without each sample routes it to the nominal expert.

    Sample b is in fold ``b % folds``; each fold is routed by :meth:`ExpertGate.fit` on the
    others (a fold whose other folds all carry one label is routed by that label)."""
    X = np.asarray(features, dtype=np.float64)
    y = np.asarray(nominal_better, dtype=bool)
    fold = np.arange(len(y)) % folds
    out = np.zeros(len(y), dtype=bool)
    for f in range(folds):
        held, rest = fold == f, fold != f
        if y[rest].all() or not y[rest].any():
            out[held] = bool(y[rest].all())
        else:
            out[held] = ExpertGate.fit(X[rest], y[rest]).to_nominal(X[held])
    return out


@dataclass(frozen=True, eq=False)
class RouteCalibration:
    """Conformal scores of a pair's routed field, one set per route (module notes).

    A score is a vertex error of the routed field over the uncertainty-trained model's bound
    at its own coverage (its normaliser times a constant per vertex, which leaves per-vertex
    conformal quantiles as they are): 0 where both are 0 (a held vertex), infinite where only
    the bound is, NaN where the bound is not finite.

    Attributes:
        expert: scores of the samples routed to the nominal expert, (m_e, n) sorted along samples.
        model: the same for the samples routed to the uncertainty-trained model, (m_u, n).
    """

    expert: VertexConformal
    model: VertexConformal

    @classmethod
    def fit(cls, to_nominal: np.ndarray, expert_errors: np.ndarray, model_errors: np.ndarray,
            model_bounds: np.ndarray) -> "RouteCalibration":
        """From held-out samples: their out-of-fold routes (B,) bool, both models' vertex errors
        (B, n) mm and the uncertainty-trained model's bounds (B, n) mm at its own coverage."""
        route = np.asarray(to_nominal, dtype=bool)
        scores = _over(np.where(route[:, None], expert_errors, model_errors), model_bounds)
        return cls(VertexConformal(np.sort(scores[route], axis=0)), VertexConformal(np.sort(scores[~route], axis=0)))

    def bounds(self, to_nominal: np.ndarray, model_bounds: np.ndarray, coverage: float) -> np.ndarray:
        """(B, n) mm bounds at ``coverage`` of fields routed as ``to_nominal`` (B,) bool, from the
        uncertainty-trained model's bounds (B, n) mm at its own coverage; NaN where a route has
        too few samples for ``coverage`` (or its scores at a vertex are not finite) or the
        model's bound is not finite."""
        route = np.asarray(to_nominal, dtype=bool)
        q = np.where(route[:, None], self.expert.quantiles(coverage)[None, :], self.model.quantiles(coverage)[None, :])
        b = np.asarray(model_bounds, dtype=np.float64)
        usable = np.isfinite(b) & np.isfinite(q)
        with np.errstate(invalid="ignore", over="ignore"):
            return np.where(usable, q * b, np.nan)

    def arrays(self) -> dict:
        """``{"expert", "model"}`` sorted scores, float32 (what :meth:`from_arrays` reads)."""
        return {"expert": self.expert.sorted_scores.astype(np.float32),
                "model": self.model.sorted_scores.astype(np.float32)}

    @classmethod
    def from_arrays(cls, arrays) -> "RouteCalibration":
        """Read :meth:`arrays`' form.

        Raises:
            ModelError: the two arrays are not (m, n) with the same n.
        """
        e, m = (np.asarray(arrays[k], dtype=np.float32) for k in ("expert", "model"))
        if e.ndim != 2 or m.ndim != 2 or e.shape[1] != m.shape[1]:
            raise ModelError(f"the pair's route scores are damaged ({e.shape}, {m.shape}); make the pair again with "
                             "`tissuecast experts`")
        return cls(VertexConformal(e), VertexConformal(m))

    def summary(self) -> dict:
        return {"expert_samples": self.expert.n_calibration, "model_samples": self.model.n_calibration}


def gate_description(gate: ExpertGate, routes: RouteCalibration | None) -> dict:
    """``describe()``'s ``expert_gate`` entry of a pair: the gate's samples and share, and how
    many samples calibrated each route's bounds (None: a pair saved before)."""
    return {"samples": gate.samples, "nominal_better": gate.nominal_better,
            "bounds_per_route": None if routes is None else routes.summary()}


def _over(errors: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """errors (B, n) over bounds (B, n): 0 / 0 is 0, e / 0 infinite, NaN where a bound is not finite."""
    b = np.asarray(bounds, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(b > 0, e / np.where(b > 0, b, 1.0), np.where(e > 0, np.inf, 0.0))
    return np.where(np.isfinite(b), r, np.nan)


def check_expert(trusted: FieldPredictor, expert: FieldPredictor) -> None:
    """Raise :class:`~tissuecast.errors.ModelError` unless ``expert`` can stand beside
    ``trusted``: both calibrated, the same mesh size, markers and auxiliary inputs."""
    if not (trusted.has_trust and expert.has_trust):
        raise ModelError("both models need calibrated error bounds and alarms (the gate reads the alarms' input "
                         "distances)")
    if (not np.array_equal(expert.markers, trusted.markers) or expert.n_vertices != trusted.n_vertices
            or expert.mesh.fingerprint() != trusted.mesh.fingerprint()):
        raise ModelError(f"the nominal expert reads markers {np.asarray(expert.markers).tolist()} on a mesh of "
                         f"{expert.n_vertices} vertices, the model {np.asarray(trusted.markers).tolist()} on "
                         f"{trusted.n_vertices} (or the meshes differ); train the expert on the same mesh with the "
                         "model's markers (one set is placed in surgery)")
    if expert.auxiliary != trusted.auxiliary:
        raise ModelError(f"the nominal expert reads the auxiliary inputs {list(expert.auxiliary.names)}, the model "
                         f"{list(trusted.auxiliary.names)}; train both with the same instruments and measured parameters")


def routing_figures(pair, fields: np.ndarray, auxiliary=None) -> dict:
    """How a model with a nominal expert routes simulated ``fields`` (B, n, 3) mm (auxiliary
    inputs (B, n_a) or None), with its input gate suspended: the mean Offset_max (mm) of both
    models, of the routed field and of the per-sample better of the two (the oracle), the share
    routed to the expert and the share routed to the better one."""
    d = pair.marker_displacements(fields).reshape(len(fields), -1)
    router = pair.predictor("mlp")
    with pair.gate_suspended():
        to_nominal = router.route(d, auxiliary)
        both = {"uncertain": router.trusted.predict(d, auxiliary=auxiliary),
                "nominal": router.expert.predict(d, auxiliary=auxiliary)}
    worst = {k: np.linalg.norm(u - fields, axis=2).max(axis=1) for k, u in both.items()}
    better = worst["nominal"] < worst["uncertain"]
    return {"count": len(fields), **{f"{k}_offset_max": float(v.mean()) for k, v in worst.items()},
            "routed_offset_max": float(np.where(to_nominal, worst["nominal"], worst["uncertain"]).mean()),
            "oracle_offset_max": float(np.minimum(worst["nominal"], worst["uncertain"]).mean()),
            "routed_to_nominal": float(to_nominal.mean()), "routed_to_better": float(np.mean(to_nominal == better))}


def _sigmoid(z: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(-z))


class NominalExpertRouter(FieldPredictor):
    """The uncertainty-trained model and the nominal expert, each sample's field routed by the gate.

    Args:
        learned: the uncertainty-trained learned predictor (what predicts with untracked markers).
        trusted: the same with its trust layer (bounds and alarm of every prediction).
        expert: the nominal expert's trusted predictor: the same mesh, markers and auxiliary inputs.
        gate: the fitted :class:`ExpertGate`.

    Raises:
        ModelError: the expert does not predict on the same mesh from the same inputs, or one
            of the two has no trust layer.
    """

    has_trust = True

    def __init__(self, learned: FieldPredictor, trusted: FieldPredictor, expert: FieldPredictor, gate: ExpertGate,
                 routes: RouteCalibration | None = None):
        check_expert(trusted, expert)
        self.learned, self.trusted, self.expert, self.gate, self.route_calibration = learned, trusted, expert, gate, routes

    # ------------------------------------------------------------------ the protocol
    @property
    def name(self) -> str:
        return self.trusted.name

    @property
    def mesh(self):
        return self.trusted.mesh

    @property
    def markers(self) -> np.ndarray:
        return self.trusted.markers

    @property
    def auxiliary(self):
        return self.trusted.auxiliary

    @property
    def supports_missing_markers(self) -> bool:
        return bool(self.learned.supports_missing_markers)

    def route(self, d: np.ndarray, a: np.ndarray | None) -> np.ndarray:
        """(B,) bool: the samples of checked displacements d (B, 3 n_d) mm and auxiliary inputs a
        (B, n_a) or None (every marker tracked) that the gate sends to the nominal expert."""
        return self.gate.to_nominal(gate_features(self.expert, self.trusted, d, a))

    def _fill(self, u: np.ndarray, to_nominal: np.ndarray, d: np.ndarray, a: np.ndarray | None) -> np.ndarray:
        """``u`` (B, n, 3) mm, its rows routed to the expert (``to_nominal`` (B,) bool) overwritten
        with the expert's fields of those rows of d (B, 3 n_d) mm and a (B, n_a) or None."""
        rows = np.flatnonzero(to_nominal)
        if len(rows):
            u[rows] = self.expert.predict_checked(d[rows], None, None if a is None else a[rows])
        return u

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None, a: np.ndarray | None = None) -> np.ndarray:
        untracked = np.zeros(len(d), bool) if missing is None else missing.any(axis=1)
        u = np.empty((len(d), self.n_vertices, 3))
        rows = np.flatnonzero(untracked)  # the gate's distances need every marker: the model alone
        if len(rows):
            u[rows] = self.learned.predict_checked(d[rows], missing[rows], None if a is None else a[rows])
        rows = np.flatnonzero(~untracked)
        if len(rows):
            dr, ar = d[rows], None if a is None else a[rows]
            to_nominal = self.route(dr, ar)
            part = self._fill(np.empty((len(rows), self.n_vertices, 3)), to_nominal, dr, ar)
            if (~to_nominal).any():
                part[~to_nominal] = self.learned.predict_checked(dr[~to_nominal], None,
                                                                 None if ar is None else ar[~to_nominal])
            u[rows] = part
        return u

    def predict_with_uncertainty(self, marker_displacements, *, missing=None, auxiliary=None):
        """Not available: the routed field comes from one of two networks, with no ensemble
        spread of its own; the error bounds of :meth:`predict_trusted` bound it."""
        raise ModelError("a model with a nominal expert gives no ensemble spread (its field comes from one of two "
                         "networks); use its error bounds instead (predict_trusted; `tissuecast predict` without "
                         "--uncertainty prints them)")

    def trusted_checked(self, d: np.ndarray, a: np.ndarray | None, *, coverage: float | None = None,
                        false_alarm: float | None = None, alarm: bool = True) -> TrustedPrediction:
        """:meth:`FieldPredictor.trusted_checked`: each sample's field from the model the gate
        routes it to, its bounds calibrated on that route (module notes), the alarm the
        uncertainty-trained model's (``alarm=False`` leaves it for :meth:`alarms`: the gate
        reads the input distances only)."""
        to_nominal = self.route(d, a)
        level = None if self.route_calibration is not None else coverage  # per route: the model's own level
        mine = self.trusted.trusted_checked(d, a, coverage=level, false_alarm=false_alarm, alarm=alarm)
        u = self._fill(np.array(mine.displacement, dtype=np.float64), to_nominal, d, a)
        bounds, level = mine.error_bound, mine.coverage
        if self.route_calibration is not None:
            level = mine.coverage if coverage is None else coverage
            routed = self.route_calibration.bounds(to_nominal, bounds, level)
            if isinstance(self.trusted, InstrumentFallback) and a is not None:
                routed[self.trusted.routes(a)] = np.nan  # an untracked instrument: calibrated for the fallback alone
            if np.isnan(routed).any():  # the model's own bound where a route cannot say
                own = bounds if level == mine.coverage else self.trusted.trusted_checked(
                    d, a, coverage=level, alarm=False).error_bound
                routed = np.where(np.isnan(routed), own, routed)
            bounds = routed
        return TrustedPrediction(u, bounds, level, mine.alarms)

    def alarms(self, marker_displacements, *, false_alarm: float | None = None, auxiliary=None):
        """The uncertainty-trained model's alarm (:meth:`.trusted.TrustedPredictor.alarms`)."""
        return self.trusted.alarms(marker_displacements, false_alarm=false_alarm, auxiliary=auxiliary)

    def describe(self) -> dict:
        return {**self.trusted.describe(), "nominal_expert": self.expert.describe(),
                "expert_gate": gate_description(self.gate, self.route_calibration)}

    def __repr__(self) -> str:
        return f"NominalExpertRouter({self.trusted!r}, expert={self.expert!r})"
