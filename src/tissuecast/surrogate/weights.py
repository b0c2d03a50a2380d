"""A trained network as plain float32 numpy arrays, and its float64 forward pass.

The numpy side of the surrogate's networks: training (:mod:`.mlp`) produces
:class:`MLPWeights`, the model folder stores them (:mod:`.storage`), the compiled predictor
(:mod:`.fastpath`) and the torch/ONNX network (:mod:`.network`) are built from them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit

from ..errors import ModelError
from .encoding import masked_input

__all__ = ["MLPWeights", "activate"]


def activate(h: np.ndarray, activation: str) -> np.ndarray:
    """The hidden-layer nonlinearity applied in place to float array ``h``: ``"relu"``
    max(h, 0) or ``"silu"`` h sigmoid(h); returns ``h``."""
    if activation == "relu":
        return np.maximum(h, 0.0, out=h)
    if activation == "silu":
        h *= expit(h)
        return h
    raise ModelError(f"unknown activation {activation!r}; use relu or silu")


@dataclass(frozen=True, eq=False)
class MLPWeights:
    """One trained network as plain float32 numpy arrays.

    Attributes:
        weights: per layer (out, in) float32; the last layer outputs n_w scaled weights.
        biases: per layer (out,) float32.
        x_mean: (3 n_d + n_a,) float32 input mean (training set): marker displacements (mm),
            then the auxiliary inputs (:mod:`.auxiliary`) in their units.
        x_std: (3 n_d + n_a,) float32 input scale.
        y_mean: (n_w,) float32 mm, PCA-weight mean.
        y_std: (n_w,) float32 mm, PCA-weight scale.
        masked: whether the input carries n_d marker-present channels (:mod:`.encoding`).
        n_auxiliary: n_a, the auxiliary inputs after the 3 n_d marker displacements.
        activation: the hidden layers' nonlinearity (:func:`activate`).
    """

    weights: tuple
    biases: tuple
    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray
    masked: bool = False
    n_auxiliary: int = 0
    activation: str = "relu"

    @property
    def n_markers(self) -> int:
        return (self.x_mean.size - self.n_auxiliary) // 3

    @property
    def hidden(self) -> tuple[int, ...]:
        return tuple(int(w.shape[0]) for w in self.weights[:-1])

    def features(self, inputs: np.ndarray, present: np.ndarray | None = None) -> np.ndarray:
        """Network input (B, 3 n_d + n_a [+ n_d]) (:mod:`.encoding`) from inputs (B, 3 n_d + n_a)
        (displacements mm, then the auxiliary inputs; finite) and present (B, n_d) bool or 1/0
        (default: every marker tracked)."""
        x = (np.asarray(inputs, dtype=np.float64) - self.x_mean) / self.x_std
        if not self.masked:
            return x
        if present is None:
            present = np.ones((x.shape[0], self.n_markers))
        return masked_input(x, np.asarray(present, dtype=np.float64))

    def predict_weights(self, inputs, present=None) -> np.ndarray:
        """PCA weights (B, n_w) mm from inputs (B, 3 n_d + n_a); float64 reference implementation
        of the forward pass."""
        h = self.features(inputs, present)
        last = len(self.weights) - 1
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ W.T.astype(np.float64) + b
            if i < last:
                activate(h, self.activation)
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
                          y_std=self.y_std[:k].copy(), masked=self.masked, n_auxiliary=self.n_auxiliary,
                          activation=self.activation)

    def tensors(self, prefix: str) -> dict[str, np.ndarray]:
        """Flat name -> array dict for safetensors/npz storage."""
        out = {f"{prefix}x_mean": self.x_mean, f"{prefix}x_std": self.x_std,
               f"{prefix}y_mean": self.y_mean, f"{prefix}y_std": self.y_std}
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            out[f"{prefix}layer{i}.weight"] = W
            out[f"{prefix}layer{i}.bias"] = b
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}

    @classmethod
    def from_tensors(cls, t: dict, prefix: str, n_layers: int, masked: bool, n_auxiliary: int = 0,
                     activation: str = "relu") -> "MLPWeights":
        try:
            return cls(
                weights=tuple(np.asarray(t[f"{prefix}layer{i}.weight"], np.float32) for i in range(n_layers)),
                biases=tuple(np.asarray(t[f"{prefix}layer{i}.bias"], np.float32) for i in range(n_layers)),
                x_mean=np.asarray(t[f"{prefix}x_mean"], np.float32),
                x_std=np.asarray(t[f"{prefix}x_std"], np.float32),
                y_mean=np.asarray(t[f"{prefix}y_mean"], np.float32),
                y_std=np.asarray(t[f"{prefix}y_std"], np.float32),
                masked=bool(masked),
                n_auxiliary=int(n_auxiliary),
                activation=str(activation),
            )
        except KeyError as exc:
            raise ModelError(f"model weights file lacks tensor {exc}; the model folder is incomplete or corrupt") from exc
