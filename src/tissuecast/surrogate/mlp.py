"""Training the MLP from marker displacements to PCA weights (torch); the result is :class:`.weights.MLPWeights`.

Inputs are the 3 n_d marker displacements (mm) followed by n_a auxiliary inputs (instrument
poses, measured parameters: :mod:`.auxiliary`; none for the paper's model), standardised per
component. With marker
masking enabled the network also gets n_d "present" channels (1 tracked, 0 missing) and a
missing marker's standardised displacement is set to 0; training then hides one random
marker in a share ``marker_dropout`` of the samples. Gaussian noise of ``noise_sigma`` mm can
be added to the marker displacements during training (tracking-noise augmentation).

Outputs are the n_w PCA weights (mm), scaled either by one global factor (``"global"``: the
loss is then proportional to the squared field error, since the PCA basis is orthonormal)
or per component (``"component"``). Training is full-data Adam with mini-batches, a
one-cycle or cosine learning-rate schedule, best-on-validation checkpointing and early
stopping; it is seeded and runs with deterministic torch algorithms on ``threads`` threads
(the same count gives the same weights bit for bit; another count may round differently).

With the simulator's sensitivities (:class:`Tangents`, ``sensitivity_weight`` > 0) each step
also fits the network's directional derivatives (forward-mode, ``torch.func.jvp``) along
``sensitivity_directions`` of each sample's load directions to the field's: the input moves
as the markers do along the direction, the output as the PCA weights do. This is Sobolev
training (Czarnecki et al., NeurIPS 2017); the loss adds ``sensitivity_weight`` times the mean
squared error of the scaled derivatives to the weights' own.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import OUTPUT_SCALINGS, SCHEDULES, SurrogateConfig
from ..errors import ModelError, require
from ..dataset.phase_stats import eta_text
from .encoding import input_width, masked_input
from .fit_stage import stage_text
from .network import build_network
from .weights import MLPWeights

__all__ = ["Tangents", "TrainingSummary", "train_mlp"]

log = logging.getLogger(__name__)

#: Smallest marker-displacement scale, as a share of the largest |displacement| (at least 1 mm):
#: a coordinate that never moves (e.g. a marker next to the pins) is not divided by ~0.
X_STD_FLOOR = 1e-6
#: An auxiliary input whose training spread is below this share of its magnitude (at least 1) is
#: constant in training (e.g. the push direction at one access site): it is scaled by that
#: magnitude instead, so that a different value at prediction time is not blown up.
AUX_CONSTANT_SHARE = 1e-6
#: Smallest PCA-weight scale (mm), absolute plus a share of the largest scale: a component
#: without variance must not blow up the loss.
Y_STD_FLOOR_ABS = 1e-9
Y_STD_FLOOR_REL = 1e-6
#: The cosine schedule decays the learning rate to this share of its peak.
COSINE_FINAL_SHARE = 1e-3
#: The validation loss is recorded at epoch 1 and every this many epochs (the training curve).
HISTORY_EVERY = 25
#: A fit still running after this many seconds says how far it is, then again every as many.
PROGRESS_SECONDS = 30.0


@dataclass(frozen=True)
class TrainingSummary:
    """What one training run did (times in s, losses in scaled-weight MSE units)."""

    seed: int
    epochs_run: int
    best_epoch: int
    best_valid_loss: float
    final_train_loss: float
    seconds: float
    stopped_early: bool
    valid_history: tuple = field(default=(), repr=False)  # (epoch, valid loss) pairs, thinned

    def as_dict(self) -> dict:
        return {
            "seed": self.seed, "epochs_run": self.epochs_run, "best_epoch": self.best_epoch,
            "best_valid_loss": self.best_valid_loss, "final_train_loss": self.final_train_loss,
            "seconds": self.seconds, "stopped_early": self.stopped_early,
            "valid_history": [list(p) for p in self.valid_history],
        }


@dataclass(frozen=True, eq=False)
class Tangents:
    """Directional derivatives of the training samples along k directions each.

    Attributes:
        inputs: (N, k, 3 n_d + n_a) how the network's inputs move per unit of a direction
            (marker displacements in mm; auxiliary inputs, e.g. a held instrument pose, 0).
        outputs: (N, k, n_w) mm, how the target PCA weights move along it.
        A direction whose rows are not finite is left out (a sample with none trains on its
        values only).
    """

    inputs: np.ndarray
    outputs: np.ndarray


@dataclass(frozen=True, eq=False)
class _Scaling:
    """Standardisation of one training run: (3 n_d + n_a,) input mean/scale and (n_w,) weight mean/scale, mm."""

    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray


@dataclass(frozen=True, eq=False)
class _Tensors:
    """Training tensors (float32): raw markers X, scaled weights Y, the marker scaling, and the
    validation network input and scaled weights."""

    X: object
    Y: object
    x_mean: object
    x_std: object
    X_valid: object
    Y_valid: object
    dX: object = None  # (N, k, n_in) scaled input tangents, None without
    dY: object = None  # (N, k, n_w) scaled output tangents
    usable: object = None  # (N, k) 1.0 where the direction is usable


@dataclass
class _Run:
    """Progress of the epoch loop: the best-on-validation parameters and the curve."""

    best_loss: float = math.inf
    best_epoch: int = 0
    best_parameters: list | None = None
    history: list = field(default_factory=list)
    train_loss: float = math.nan
    epochs: int = 0
    stopped_early: bool = False


@contextlib.contextmanager
def _deterministic(torch, threads: int = 1):
    """``threads`` torch threads and deterministic algorithms, restored afterwards."""
    before = torch.get_num_threads()
    det = torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(int(threads))
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(det)
        torch.set_num_threads(before)


def _check_xy(X, Y, name, n_auxiliary: int = 0):
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    nd3 = X.shape[1] - n_auxiliary if X.ndim == 2 else -1
    if X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0] or nd3 < 3 or nd3 % 3 or X.shape[0] == 0:
        raise ModelError(f"{name}: need inputs (N, 3 n_d + {n_auxiliary}) and weights (N, n_w) with N >= 1, "
                         f"got {X.shape} and {Y.shape}")
    if not (np.isfinite(X).all() and np.isfinite(Y).all()):
        raise ModelError(f"{name} data contain NaN or inf")
    return X, Y


def _check_inputs(X_train, Y_train, X_valid, Y_valid, config: SurrogateConfig, n_auxiliary: int = 0):
    """Checked float64 arrays ``(X, Y, Xv, Yv)``; settings the config file would have refused."""
    X, Y = _check_xy(X_train, Y_train, "training", n_auxiliary)
    Xv, Yv = _check_xy(X_valid, Y_valid, "validation", n_auxiliary)
    if Xv.shape[1] != X.shape[1] or Yv.shape[1] != Y.shape[1]:
        raise ModelError(f"validation shapes {Xv.shape}, {Yv.shape} do not match training {X.shape}, {Y.shape}")
    if config.schedule not in SCHEDULES:
        raise ModelError(f"unknown schedule {config.schedule!r}; use {', '.join(SCHEDULES)}")
    if config.output_scaling not in OUTPUT_SCALINGS:
        raise ModelError(f"unknown output_scaling {config.output_scaling!r}; use {', '.join(OUTPUT_SCALINGS)}")
    return X, Y, Xv, Yv


def _scaling(X: np.ndarray, Y: np.ndarray, output_scaling: str, n_auxiliary: int = 0) -> _Scaling:
    """Per-component input standardisation (markers, then auxiliary inputs: :data:`AUX_CONSTANT_SHARE`);
    PCA-weight scaling per component or one global factor."""
    markers = X[:, :X.shape[1] - n_auxiliary]
    x_std = np.maximum(markers.std(axis=0), X_STD_FLOOR * max(1.0, float(np.abs(markers).max())))
    if n_auxiliary:
        aux = X[:, X.shape[1] - n_auxiliary:]
        size = np.maximum(1.0, np.abs(aux).max(axis=0))
        spread = aux.std(axis=0)
        x_std = np.concatenate([x_std, np.where(spread > AUX_CONSTANT_SHARE * size, spread, size)])
    y_std = Y.std(axis=0)
    if output_scaling == "global":
        y_std = np.full_like(y_std, math.sqrt(float(np.mean(y_std**2))))
    y_std = np.maximum(y_std, Y_STD_FLOOR_ABS + Y_STD_FLOOR_REL * float(y_std.max(initial=0.0)))
    return _Scaling(X.mean(axis=0), x_std, Y.mean(axis=0), y_std)


def _tensors(torch, X, Y, Xv, Yv, s: _Scaling, masked: bool, n_markers: int, tangents: Tangents | None = None) -> _Tensors:
    f32 = torch.float32
    xm, xs = torch.as_tensor(s.x_mean, dtype=f32), torch.as_tensor(s.x_std, dtype=f32)
    Xvt = (torch.as_tensor(Xv, dtype=f32) - xm) / xs
    if masked:  # validation with every marker tracked
        Xvt = masked_input(Xvt, torch.ones(Xvt.shape[0], n_markers), torch)
    extra = {}
    if tangents is not None:
        ok = np.isfinite(tangents.inputs).all(axis=2) & np.isfinite(tangents.outputs).all(axis=2)  # (N, k)
        extra = {"dX": torch.as_tensor(np.where(ok[:, :, None], tangents.inputs, 0.0) / s.x_std, dtype=f32),
                 "dY": torch.as_tensor(np.where(ok[:, :, None], tangents.outputs, 0.0) / s.y_std, dtype=f32),
                 "usable": torch.as_tensor(ok, dtype=f32)}
    return _Tensors(X=torch.as_tensor(X, dtype=f32), Y=torch.as_tensor((Y - s.y_mean) / s.y_std, dtype=f32),
                    x_mean=xm, x_std=xs, X_valid=Xvt, Y_valid=torch.as_tensor((Yv - s.y_mean) / s.y_std, dtype=f32),
                    **extra)


def _scheduler(torch, optimizer, c: SurrogateConfig, total_steps: int):
    """The learning-rate schedule over all optimizer steps (None: constant)."""
    if c.schedule == "onecycle":
        return torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=c.learning_rate, total_steps=total_steps)
    if c.schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total_steps,
                                                          eta_min=c.learning_rate * COSINE_FINAL_SHARE)
    return None


def _batch_input(torch, t: _Tensors, idx, c: SurrogateConfig, gen, masked: bool, n_markers: int):
    """Network input of one mini-batch: tracking noise (on the markers), standardisation, one
    marker hidden in a share ``marker_dropout`` of the samples."""
    xb = t.X[idx]
    if c.noise_sigma > 0:
        nd3 = 3 * n_markers
        noise = c.noise_sigma * torch.randn((xb.shape[0], nd3), generator=gen)
        xb = xb + noise if xb.shape[1] == nd3 else torch.cat([xb[:, :nd3] + noise, xb[:, nd3:]], dim=1)
    xb = (xb - t.x_mean) / t.x_std
    if not masked:
        return xb
    n_d = n_markers
    present = torch.ones(len(idx), n_d)
    drop = torch.rand(len(idx), generator=gen) < c.marker_dropout
    which = torch.randint(0, n_d, (len(idx),), generator=gen)
    present[drop, which[drop]] = 0.0
    return masked_input(xb, present, torch)


def _train_epoch(torch, net, optimizer, scheduler, t: _Tensors, c: SurrogateConfig, gen, masked: bool,
                 n_markers: int) -> float:
    """One pass over the shuffled training set; returns the mean training loss."""
    net.train()
    N = t.X.shape[0]
    bs = min(int(c.batch_size), N)
    perm = torch.randperm(N, generator=gen)
    total = 0.0
    for s in range(math.ceil(N / bs)):
        idx = perm[s * bs:(s + 1) * bs]
        xin = _batch_input(torch, t, idx, c, gen, masked, n_markers)
        loss = torch.nn.functional.mse_loss(net(xin), t.Y[idx])
        if t.dX is not None:
            loss = loss + c.sensitivity_weight * _tangent_loss(torch, net, t, idx, xin, c.sensitivity_directions, gen)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        total += float(loss.detach()) * len(idx)
    return total / N


def _tangent_loss(torch, net, t: _Tensors, idx, xin, directions: int, gen):
    """Mean squared error of the network's scaled directional derivatives at the batch inputs
    ``xin`` along ``directions`` random directions of each sample that has tangents (the
    unusable ones, not finite, left out)."""
    has = t.usable[idx].any(dim=1)
    which = idx[has]
    if not len(which):
        return torch.zeros(())
    k = torch.randint(0, t.dX.shape[1], (len(which), directions), generator=gen)
    x = xin[has].repeat_interleave(directions, 0)
    dx = t.dX[which[:, None], k].reshape(x.shape)
    _, jv = torch.func.jvp(net, (x,), (dx,))
    w = t.usable[which[:, None], k].reshape(-1, 1)
    count = w.sum()
    if not count > 0:
        return torch.zeros(())
    return (w * (jv - t.dY[which[:, None], k].reshape(jv.shape)) ** 2).sum() / (count * jv.shape[1])


class _Progress:
    """A log line every :data:`PROGRESS_SECONDS` of a fit: the epoch, the validation loss, the time left."""

    def __init__(self, name: str, epochs: int) -> None:
        self.name, self.epochs = name, epochs
        self.t0 = self.last = time.monotonic()

    def epoch(self, run: _Run, vloss: float) -> None:
        now = time.monotonic()
        if now - self.last < PROGRESS_SECONDS or run.epochs >= self.epochs:
            return
        self.last = now
        left = (now - self.t0) / run.epochs * (self.epochs - run.epochs)
        log.info("training %s: epoch %d/%d, validation loss %.3g (best %.3g at epoch %d), %s so far, about %s left "
                 "(less if it stops early)", self.name, run.epochs, self.epochs, vloss, run.best_loss, run.best_epoch,
                 eta_text(now - self.t0), eta_text(left))


def _fit(torch, net, t: _Tensors, c: SurrogateConfig, gen, masked: bool, n_markers: int, name: str = "MLP") -> _Run:
    """Adam epochs with best-on-validation checkpointing and early stopping after ``patience``;
    ``name`` is the fit's name in its progress lines."""
    # fused: one kernel updates every parameter (no Python loop over them per step)
    optimizer = torch.optim.Adam(net.parameters(), lr=c.learning_rate, weight_decay=c.weight_decay, fused=True)
    N = t.X.shape[0]
    scheduler = _scheduler(torch, optimizer, c, c.epochs * math.ceil(N / min(int(c.batch_size), N)))
    run = _Run()
    progress = _Progress(name, c.epochs)
    for epoch in range(1, c.epochs + 1):
        run.epochs = epoch
        run.train_loss = _train_epoch(torch, net, optimizer, scheduler, t, c, gen, masked, n_markers)
        net.eval()
        with torch.no_grad():
            vloss = float(torch.nn.functional.mse_loss(net(t.X_valid), t.Y_valid))
        if vloss < run.best_loss:
            run.best_loss, run.best_epoch = vloss, epoch
            run.best_parameters = [p.detach().clone() for p in net.parameters()]
        if epoch == 1 or epoch % HISTORY_EVERY == 0:
            run.history.append((epoch, vloss))
        progress.epoch(run, vloss)
        if c.patience and epoch - run.best_epoch >= c.patience:
            run.stopped_early = True
            break
    return run


def _weights(torch, net, parameters: list, s: _Scaling, masked: bool, n_auxiliary: int,
             activation: str = "relu") -> MLPWeights:
    """The network with ``parameters`` loaded, as float32 numpy :class:`MLPWeights`."""
    with torch.no_grad():
        for p, b in zip(net.parameters(), parameters):
            p.copy_(b)
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    return MLPWeights(
        weights=tuple(m.weight.detach().numpy().astype(np.float32).copy() for m in linears),
        biases=tuple(m.bias.detach().numpy().astype(np.float32).copy() for m in linears),
        x_mean=s.x_mean.astype(np.float32), x_std=s.x_std.astype(np.float32),
        y_mean=s.y_mean.astype(np.float32), y_std=s.y_std.astype(np.float32),
        masked=masked, n_auxiliary=n_auxiliary, activation=activation,
    )


def train_mlp(X_train, Y_train, X_valid, Y_valid, config: SurrogateConfig | None = None, *,
              seed: int | None = None, n_auxiliary: int = 0,
              tangents: Tangents | None = None) -> tuple[MLPWeights, TrainingSummary]:
    """Train one network.

    Args:
        X_train: (N, 3 n_d + n_a) inputs: marker displacements (mm), then n_a auxiliary inputs.
        Y_train: (N, n_w) PCA weights, mm.
        X_valid: (M, 3 n_d + n_a) validation inputs (M >= 1).
        Y_valid: (M, n_w) validation PCA weights, mm.
        config: the hyper-parameters (``hidden``, ``epochs``, ``batch_size``, ``learning_rate``,
            ``patience``, ``schedule``, ``output_scaling``, ``weight_decay``, ``noise_sigma``,
            ``marker_dropout``); None: the defaults.
        seed: seed of this network (default ``config.seed``).
        n_auxiliary: n_a, the auxiliary inputs at the end of each input row (:mod:`.auxiliary`).
        tangents: the training samples' directional derivatives (:class:`Tangents`), fitted
            with weight ``sensitivity_weight``; None (or a weight of 0): values only.

    Returns:
        The best-on-validation weights and a :class:`TrainingSummary`.
    """
    torch = require("torch", "learn", "training the surrogate MLP")
    c = SurrogateConfig() if config is None else config
    seed = c.seed if seed is None else int(seed)
    n_a = int(n_auxiliary)
    X, Y, Xv, Yv = _check_inputs(X_train, Y_train, X_valid, Y_valid, c, n_a)
    masked = c.marker_dropout > 0
    n_markers = (X.shape[1] - n_a) // 3
    scaling = _scaling(X, Y, c.output_scaling, n_a)
    t0 = time.perf_counter()
    with _deterministic(torch, c.threads):
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        use = tangents if tangents is not None and c.sensitivity_weight > 0 else None
        if use is not None and (use.inputs.shape[::2] != (X.shape[0], X.shape[1]) or use.outputs.shape[::2] != Y.shape
                                or use.inputs.shape[1] != use.outputs.shape[1]):
            raise ModelError(f"tangents {use.inputs.shape}, {use.outputs.shape} do not match the training data "
                             f"{X.shape}, {Y.shape}")
        if use is not None and masked:
            raise ModelError("tangents need marker_dropout = 0")
        tensors = _tensors(torch, X, Y, Xv, Yv, scaling, masked, n_markers, use)
        name = f"MLP {list(c.hidden)} seed {seed}{stage_text()}"
        if use is not None:
            log.info("training %s on %d samples and their sensitivities (%d directions a sample a step, up to %d epochs)",
                     name, X.shape[0], c.sensitivity_directions, c.epochs)
        net = build_network(torch, input_width(n_markers, masked, n_a), c.hidden, Y.shape[1], c.activation)
        run = _fit(torch, net, tensors, c, gen, masked, n_markers, name)
        weights = _weights(torch, net, run.best_parameters, scaling, masked, n_a, c.activation)
    summary = TrainingSummary(
        seed=seed, epochs_run=run.epochs, best_epoch=run.best_epoch, best_valid_loss=run.best_loss,
        final_train_loss=run.train_loss, seconds=time.perf_counter() - t0, stopped_early=run.stopped_early,
        valid_history=tuple(run.history),
    )
    log.info("trained %s: %d epochs, best validation loss %.3g at epoch %d, %.1f s",
             name, run.epochs, run.best_loss, run.best_epoch, summary.seconds)
    return weights, summary
