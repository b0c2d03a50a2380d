"""The MLP from marker displacements to PCA weights: training (torch) and plain weights.

Inputs are the 3 n_d marker displacements (mm), standardised per component. With marker
masking enabled the network also gets n_d "present" channels (1 tracked, 0 missing) and a
missing marker's standardised displacement is set to 0; training then hides one random
marker in a share ``marker_dropout`` of the samples. Gaussian noise of ``noise_sigma`` mm can
be added to the marker displacements during training (tracking-noise augmentation).

Outputs are the n_w PCA weights (mm), scaled either by one global factor (``"global"``: the
loss is then proportional to the squared field error, since the PCA basis is orthonormal)
or per component (``"component"``). Training is full-data Adam with mini-batches, a
one-cycle or cosine learning-rate schedule, best-on-validation checkpointing and early
stopping; it is seeded and runs with deterministic torch algorithms on one thread.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ModelError, require
from .network import build_network

__all__ = ["MLPWeights", "TrainingSummary", "TrainOptions", "train_mlp"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainOptions:
    """Training hyper-parameters (see :class:`tissuecast.config.SurrogateConfig`)."""

    hidden: tuple[int, ...] = (128, 64)
    epochs: int = 2500
    batch_size: int = 128
    learning_rate: float = 3e-3
    patience: int = 250
    schedule: str = "onecycle"
    output_scaling: str = "global"
    weight_decay: float = 0.0
    noise_sigma: float = 0.0
    marker_dropout: float = 0.0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class MLPWeights:
    """One trained network as plain float32 numpy arrays.

    Attributes:
        weights: per layer (out, in) float32; the last layer outputs n_w scaled weights.
        biases: per layer (out,) float32.
        x_mean: (3 n_d,) float32 mm, marker-displacement mean (training set).
        x_std: (3 n_d,) float32 mm, marker-displacement scale.
        y_mean: (n_w,) float32 mm, PCA-weight mean.
        y_std: (n_w,) float32 mm, PCA-weight scale.
        masked: whether the input carries n_d marker-present channels after the 3 n_d values.
    """

    weights: tuple
    biases: tuple
    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray
    masked: bool = False

    @property
    def n_markers(self) -> int:
        return self.x_mean.size // 3

    @property
    def hidden(self) -> tuple[int, ...]:
        return tuple(int(w.shape[0]) for w in self.weights[:-1])

    def features(self, marker_displacements: np.ndarray, present: np.ndarray | None = None) -> np.ndarray:
        """Network input (B, 3 n_d [+ n_d]) from displacements (B, 3 n_d) mm and present (B, n_d) bool."""
        x = (np.asarray(marker_displacements, dtype=np.float64) - self.x_mean) / self.x_std
        if not self.masked:
            return x
        if present is None:
            present = np.ones((x.shape[0], self.n_markers))
        pres = np.asarray(present, dtype=np.float64)
        x = np.where(np.repeat(pres, 3, axis=1) > 0, x, 0.0)
        return np.concatenate([x, pres], axis=1)

    def predict_weights(self, marker_displacements, present=None) -> np.ndarray:
        """PCA weights (B, n_w) mm; float64 reference implementation of the forward pass."""
        h = self.features(marker_displacements, present)
        last = len(self.weights) - 1
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ W.T.astype(np.float64) + b
            if i < last:
                np.maximum(h, 0.0, out=h)
        return h * self.y_std + self.y_mean

    def truncated(self, n_components: int) -> "MLPWeights":
        """The same network predicting only the first ``n_components`` PCA weights (the last
        layer's rows and the output scaling cut; the other outputs were independent rows)."""
        k = int(n_components)
        if not 1 <= k <= self.y_mean.size:
            raise ModelError(f"n_components must be in [1, {self.y_mean.size}], got {n_components}")
        return MLPWeights(weights=(*self.weights[:-1], self.weights[-1][:k].copy()),
                          biases=(*self.biases[:-1], self.biases[-1][:k].copy()),
                          x_mean=self.x_mean, x_std=self.x_std, y_mean=self.y_mean[:k].copy(),
                          y_std=self.y_std[:k].copy(), masked=self.masked)

    def tensors(self, prefix: str) -> dict[str, np.ndarray]:
        """Flat name -> array dict for safetensors/npz storage."""
        out = {f"{prefix}x_mean": self.x_mean, f"{prefix}x_std": self.x_std,
               f"{prefix}y_mean": self.y_mean, f"{prefix}y_std": self.y_std}
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            out[f"{prefix}layer{i}.weight"] = W
            out[f"{prefix}layer{i}.bias"] = b
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}

    @classmethod
    def from_tensors(cls, t: dict, prefix: str, n_layers: int, masked: bool) -> "MLPWeights":
        try:
            return cls(
                weights=tuple(np.asarray(t[f"{prefix}layer{i}.weight"], np.float32) for i in range(n_layers)),
                biases=tuple(np.asarray(t[f"{prefix}layer{i}.bias"], np.float32) for i in range(n_layers)),
                x_mean=np.asarray(t[f"{prefix}x_mean"], np.float32),
                x_std=np.asarray(t[f"{prefix}x_std"], np.float32),
                y_mean=np.asarray(t[f"{prefix}y_mean"], np.float32),
                y_std=np.asarray(t[f"{prefix}y_std"], np.float32),
                masked=bool(masked),
            )
        except KeyError as exc:
            raise ModelError(f"model weights file lacks tensor {exc}; the model folder is incomplete or corrupt") from exc


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


@contextlib.contextmanager
def _deterministic(torch):
    """One thread and deterministic algorithms, restored afterwards."""
    threads = torch.get_num_threads()
    det = torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(det)
        torch.set_num_threads(threads)


def _check_xy(X, Y, name):
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    if X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0] or X.shape[1] % 3 or X.shape[0] == 0:
        raise ModelError(f"{name}: need markers (N, 3 n_d) and weights (N, n_w) with N >= 1, got {X.shape} and {Y.shape}")
    if not (np.isfinite(X).all() and np.isfinite(Y).all()):
        raise ModelError(f"{name} data contain NaN or inf")
    return X, Y


def train_mlp(X_train, Y_train, X_valid, Y_valid, options: TrainOptions = TrainOptions()) -> tuple[MLPWeights, TrainingSummary]:
    """Train one network.

    Args:
        X_train: (N, 3 n_d) marker displacements, mm.
        Y_train: (N, n_w) PCA weights, mm.
        X_valid: (M, 3 n_d) validation marker displacements, mm (M >= 1).
        Y_valid: (M, n_w) validation PCA weights, mm.
        options: hyper-parameters.

    Returns:
        The best-on-validation weights and a :class:`TrainingSummary`.
    """
    torch = require("torch", "learn", "training the surrogate MLP")
    o = options
    X, Y = _check_xy(X_train, Y_train, "training")
    Xv, Yv = _check_xy(X_valid, Y_valid, "validation")
    if Xv.shape[1] != X.shape[1] or Yv.shape[1] != Y.shape[1]:
        raise ModelError(f"validation shapes {Xv.shape}, {Yv.shape} do not match training {X.shape}, {Y.shape}")
    if o.schedule not in ("onecycle", "cosine", "constant"):
        raise ModelError(f"unknown schedule {o.schedule!r}; use onecycle, cosine or constant")
    if o.output_scaling not in ("global", "component"):
        raise ModelError(f"unknown output_scaling {o.output_scaling!r}; use global or component")
    n_d = X.shape[1] // 3
    masked = o.marker_dropout > 0
    x_mean = X.mean(axis=0)
    x_std = np.maximum(X.std(axis=0), 1e-6 * max(1.0, float(np.abs(X).max())))
    y_mean = Y.mean(axis=0)
    y_std = Y.std(axis=0)
    if o.output_scaling == "global":
        y_std = np.full_like(y_std, math.sqrt(float(np.mean(y_std**2))))
    y_std = np.maximum(y_std, 1e-9 + 1e-6 * float(y_std.max(initial=0.0)))
    t0 = time.perf_counter()
    with _deterministic(torch):
        torch.manual_seed(o.seed)
        gen = torch.Generator().manual_seed(o.seed)
        f32 = torch.float32
        Xt = torch.as_tensor(X, dtype=f32)
        Yt = torch.as_tensor((Y - y_mean) / y_std, dtype=f32)
        xm, xs = torch.as_tensor(x_mean, dtype=f32), torch.as_tensor(x_std, dtype=f32)
        Xvt = (torch.as_tensor(Xv, dtype=f32) - xm) / xs
        if masked:
            Xvt = torch.cat([Xvt, torch.ones(Xvt.shape[0], n_d)], dim=1)
        Yvt = torch.as_tensor((Yv - y_mean) / y_std, dtype=f32)
        net = build_network(torch, X.shape[1] + (n_d if masked else 0), o.hidden, Y.shape[1])
        opt = torch.optim.Adam(net.parameters(), lr=o.learning_rate, weight_decay=o.weight_decay)
        N = X.shape[0]
        bs = min(int(o.batch_size), N)
        steps = math.ceil(N / bs)
        if o.schedule == "onecycle":
            sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=o.learning_rate, total_steps=o.epochs * steps)
        elif o.schedule == "cosine":
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=o.epochs * steps, eta_min=o.learning_rate * 1e-3)
        else:
            sched = None
        best = (math.inf, 0, None)
        history = []
        train_loss = math.nan
        epoch = 0
        stopped = False
        for epoch in range(1, o.epochs + 1):
            net.train()
            perm = torch.randperm(N, generator=gen)
            total = 0.0
            for s in range(steps):
                idx = perm[s * bs:(s + 1) * bs]
                xb = Xt[idx]
                if o.noise_sigma > 0:
                    xb = xb + o.noise_sigma * torch.randn(xb.shape, generator=gen)
                xb = (xb - xm) / xs
                if masked:
                    pres = torch.ones(len(idx), n_d)
                    drop = torch.rand(len(idx), generator=gen) < o.marker_dropout
                    which = torch.randint(0, n_d, (len(idx),), generator=gen)
                    pres[drop, which[drop]] = 0.0
                    xb = torch.cat([xb * pres.repeat_interleave(3, dim=1), pres], dim=1)
                loss = torch.nn.functional.mse_loss(net(xb), Yt[idx])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                if sched is not None:
                    sched.step()
                total += float(loss.detach()) * len(idx)
            train_loss = total / N
            net.eval()
            with torch.no_grad():
                vloss = float(torch.nn.functional.mse_loss(net(Xvt), Yvt))
            if vloss < best[0]:
                best = (vloss, epoch, [p.detach().clone() for p in net.parameters()])
            if epoch == 1 or epoch % 25 == 0:
                history.append((epoch, vloss))
            if o.patience and epoch - best[1] >= o.patience:
                stopped = True
                break
        with torch.no_grad():
            for p, b in zip(net.parameters(), best[2]):
                p.copy_(b)
        linears = [m for m in net if isinstance(m, torch.nn.Linear)]
        weights = MLPWeights(
            weights=tuple(m.weight.detach().numpy().astype(np.float32).copy() for m in linears),
            biases=tuple(m.bias.detach().numpy().astype(np.float32).copy() for m in linears),
            x_mean=x_mean.astype(np.float32), x_std=x_std.astype(np.float32),
            y_mean=y_mean.astype(np.float32), y_std=y_std.astype(np.float32),
            masked=masked,
        )
    summary = TrainingSummary(
        seed=o.seed, epochs_run=epoch, best_epoch=best[1], best_valid_loss=best[0],
        final_train_loss=train_loss, seconds=time.perf_counter() - t0, stopped_early=stopped,
        valid_history=tuple(history),
    )
    log.info("trained MLP %s seed %d: %d epochs, best valid %.3g at %d, %.1f s",
             list(o.hidden), o.seed, epoch, best[0], best[1], summary.seconds)
    return weights, summary
