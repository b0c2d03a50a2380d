"""Fitting the learned predictor's parts in order: the number of PCA components, the PCA basis
(training fields only), the quadratic head, the network ensemble on the head's residual, and
(validation rule) the cut of every part to the chosen number of components.

The result is a :class:`~.network_predictor.NetworkPredictor` with the record of the choices
(:class:`NetworkFit`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass

import numpy as np

from ..config import SurrogateConfig
from .auxiliary import MARKERS_ONLY, AuxiliaryInputs
from .component_choice import choose_by_validation, components_to_train
from .decoder import fit_decoder
from .fit_stage import fit_stage
from .head import fit_head, truncated_head
from .mlp import Tangents, TrainingSummary, train_mlp
from .network_predictor import NetworkPredictor
from .pca import PCACurve
from .ridge import marker_columns
from .weights import MLPWeights

__all__ = ["NetworkFit", "fit_network", "train_members", "ENSEMBLE_SEED_STRIDE"]

log = logging.getLogger(__name__)

#: Member k of an ensemble trains with seed ``surrogate.seed + ENSEMBLE_SEED_STRIDE * k``: far
#: enough apart that runs with neighbouring seeds share no member.
ENSEMBLE_SEED_STRIDE = 1000


@dataclass(frozen=True, eq=False)
class NetworkFit:
    """A fitted :class:`NetworkPredictor` and how it was chosen.

    Attributes:
        predictor: the fitted predictor.
        choice: the rule behind n_w and its curves, the head's size (``pca_choice`` of the model).
        curve: the paper rule's cross-validated PCA curve, or None.
        summaries: one :class:`TrainingSummary` per member.
        pca_seconds: seconds spent choosing n_w before the PCA fit.
    """

    predictor: NetworkPredictor
    choice: dict
    curve: PCACurve | None
    summaries: list
    pca_seconds: float


def train_members(Xt, Yt, Xv, Yv, config: SurrogateConfig, n_auxiliary: int = 0,
                  tangents: Tangents | None = None) -> tuple[list[MLPWeights], list[TrainingSummary]]:
    """The ensemble's networks (member k seeded ``seed + ENSEMBLE_SEED_STRIDE k``) and their training summaries.

    Args:
        Xt, Xv: (N_t, 3 n_d + n_a), (N_v, 3 n_d + n_a) inputs: marker displacements (mm), then
            the auxiliary inputs.
        Yt, Yv: (N_t, n_w), (N_v, n_w) target PCA weights, mm.
        config: the surrogate settings (``ensemble``, ``seed`` and the training settings).
        n_auxiliary: n_a.
        tangents: the training samples' directional derivatives (:class:`~.mlp.Tangents`), or None.
    """
    members, summaries = [], []
    for k in range(config.ensemble):
        with fit_stage(f"member {k + 1}/{config.ensemble}") if config.ensemble > 1 else contextlib.nullcontext():
            w, s = train_mlp(Xt, Yt, Xv, Yv, config, seed=config.seed + ENSEMBLE_SEED_STRIDE * k,
                             n_auxiliary=n_auxiliary, tangents=tangents)
        members.append(w)
        summaries.append(s)
    return members, summaries


def fit_network(Ut: np.ndarray, Uv: np.ndarray, markers: np.ndarray, mesh, config: SurrogateConfig,
                At: np.ndarray | None = None, Av: np.ndarray | None = None,
                auxiliary: AuxiliaryInputs = MARKERS_ONLY, St: np.ndarray | None = None) -> NetworkFit:
    """Fit the PCA + (head +) MLP predictor.

    Args:
        Ut: (N_t, 3 n) training fields, float64 mm (finite).
        Uv: (N_v, 3 n) validation fields, float64 mm (checkpointing, the head's size, n_w).
        markers: (n_d,) int64 0-based marker ids.
        mesh: the :class:`TetMesh` with n vertices.
        config: the surrogate settings.
        At, Av: (N_t, n_a), (N_v, n_a) auxiliary inputs of the samples (``auxiliary.names``,
            finite), read by the head and the networks after the markers; None without.
        auxiliary: what they are (:class:`~.auxiliary.AuxiliaryInputs`).
        St: (N_t, k, n, 3) the training fields' sensitivities along k load directions, mm
            (:mod:`tissuecast.dataset.sensitivities`; NaN for a sample without), trained on
            with weight ``sensitivity_weight``; None: without.
    """
    c = config
    t0 = time.perf_counter()
    n_w, rule, curve = components_to_train(c, Ut)
    t_pca = time.perf_counter()
    basis = fit_decoder(Ut, n_w, mesh, c)
    cols = marker_columns(markers)
    Xt, Xv = Ut[:, cols], Uv[:, cols]
    if auxiliary.width:
        Xt, Xv = np.hstack([Xt, At]), np.hstack([Xv, Av])
    Yt, Yv = basis.transform(Ut), basis.transform(Uv)
    head, head_info = None, {"dims": None}
    if c.head == "quadratic" and c.marker_dropout == 0:
        head, head_info = fit_head(Xt, Yt, Xv, Uv, basis, c.head_dims)
    elif c.head == "quadratic":
        log.info("no quadratic head: it needs every marker, and marker_dropout > 0 trains for missing ones")
    head_t = None if head is None else head.predict(Xt)
    head_v = None if head is None else head.predict(Xv)
    tangents = None if St is None or not c.sensitivity_weight > 0 else _tangents(St, basis, markers, Xt, head)
    members, summaries = train_members(Xt, Yt if head is None else Yt - head_t, Xv,
                                       Yv if head is None else Yv - head_v, c, auxiliary.width, tangents)
    choice = {"rule": rule, "n_components": n_w, "head": head_info}
    if not c.n_components and c.pca_rule == "validation":
        n_w, curve_v = choose_by_validation(members, basis, Xv, Uv, head_v)
        basis, members = basis.truncated(n_w), [m.truncated(n_w) for m in members]
        head = truncated_head(head, n_w)
        choice.update(n_components=n_w, trained_components=int(curve_v["n_components"][-1]), validation_curve=curve_v)
    return NetworkFit(NetworkPredictor(mesh, markers, basis, members, head, auxiliary), choice, curve, summaries,
                      t_pca - t0)


#: Training samples whose sensitivities are projected on the decoder at once (bounds the memory).
_TANGENT_CHUNK = 64


def _tangents(St: np.ndarray, basis, markers: np.ndarray, Xt: np.ndarray, head) -> Tangents:
    """The networks' tangents: the markers' and the decoder coefficients' motion along each
    sensitivity direction, less the quadratic head's (its central difference, exact for a
    quadratic)."""
    N, k = St.shape[:2]
    n_in = Xt.shape[1]
    dX = np.zeros((N, k, n_in))
    dX[:, :, :3 * len(markers)] = np.asarray(St[:, :, markers, :], dtype=np.float64).reshape(N, k, -1)
    zero = basis.transform(np.zeros((1, basis.n_features)))
    dY = np.empty((N, k, basis.n_components))
    for a in range(0, N, _TANGENT_CHUNK):
        rows = np.asarray(St[a:a + _TANGENT_CHUNK], dtype=np.float64).reshape(-1, basis.n_features)
        dY[a:a + _TANGENT_CHUNK] = (basis.transform(rows) - zero).reshape(-1, k, basis.n_components)
    if head is not None:
        x = np.repeat(Xt, k, axis=0)
        step = dX.reshape(N * k, n_in)
        dY -= (0.5 * (head.predict(x + step) - head.predict(x - step))).reshape(N, k, -1)
    return Tangents(dX, dY)
