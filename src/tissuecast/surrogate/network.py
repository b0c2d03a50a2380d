"""Torch modules of the surrogate: the MLP stack and the whole marker -> field network."""

from __future__ import annotations

import numpy as np

from ..errors import require
from .encoding import masked_input
from .weights import MLPWeights

__all__ = ["build_network", "torch_network"]


def build_network(torch, n_in: int, hidden, n_out: int, activation: str = "relu"):
    """Linear stack n_in -> hidden... -> n_out with ``activation`` (relu or silu) between
    (torch.nn.Sequential)."""
    layers, width = [], n_in
    act = {"relu": torch.nn.ReLU, "silu": torch.nn.SiLU}[activation]
    for h in hidden:
        layers += [torch.nn.Linear(width, int(h)), act()]
        width = int(h)
    layers.append(torch.nn.Linear(width, n_out))
    return torch.nn.Sequential(*layers)


def torch_network(members: list[MLPWeights], components: np.ndarray, mean: np.ndarray, head=None):
    """A torch module mapping marker displacements (and auxiliary inputs) to the full field.

    Inputs, in this order: ``markers`` (B, n_d, 3) float32 mm; for a model with n_a > 0
    auxiliary inputs (:mod:`.auxiliary`) ``auxiliary`` (B, n_a) float32 in their units; for
    masked models ``present`` (B, n_d) float32 1/0 (optional, default all tracked). Output
    (B, n, 3) float32 mm: the ensemble average of the members' PCA weights, plus the quadratic
    ``head``'s (:mod:`.head`) when given, reconstructed with ``components`` (n_w, 3 n) and
    ``mean`` (3 n,).
    """
    torch = require("torch", "learn", "the torch/ONNX surrogate network")
    first = members[0]

    class FieldNetwork(torch.nn.Module):
        def __init__(self):
            super().__init__()
            f32 = torch.float32
            self.masked = first.masked
            self.n_auxiliary = first.n_auxiliary
            self.nets = torch.nn.ModuleList()
            for m in members:
                net = build_network(torch, m.weights[0].shape[1], m.hidden, m.weights[-1].shape[0], m.activation)
                with torch.no_grad():
                    for lin, W, b in zip([x for x in net if isinstance(x, torch.nn.Linear)], m.weights, m.biases):
                        lin.weight.copy_(torch.as_tensor(W))
                        lin.bias.copy_(torch.as_tensor(b))
                self.nets.append(net)
            self.register_buffer("x_mean", torch.as_tensor(first.x_mean, dtype=f32))
            self.register_buffer("x_std", torch.as_tensor(first.x_std, dtype=f32))
            self.register_buffer("y_mean", torch.as_tensor(first.y_mean, dtype=f32))
            self.register_buffer("y_std", torch.as_tensor(first.y_std, dtype=f32))
            self.register_buffer("components", torch.as_tensor(components, dtype=f32))
            self.register_buffer("mean", torch.as_tensor(mean, dtype=f32))
            self.has_head = head is not None
            self.has_quad = self.has_head and len(head.directions) > 0
            if self.has_head:
                n_in = head.mean.size
                a, b = np.triu_indices(len(head.directions))
                for name, v in (("h_mean", head.mean), ("h_scale", head.scale), ("h_dirs", head.directions.T),
                                ("h_const", head.coef[0]), ("h_lin", head.coef[1:1 + n_in]), ("h_quad", head.coef[1 + n_in:])):
                    self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(v), dtype=f32))
                self.register_buffer("h_a", torch.as_tensor(a, dtype=torch.int64))
                self.register_buffer("h_b", torch.as_tensor(b, dtype=torch.int64))

        def forward(self, markers, *extra):
            raw = markers.reshape(markers.shape[0], -1)
            if self.n_auxiliary:
                raw = torch.cat([raw, extra[0]], dim=1)
                extra = extra[1:]
            present = extra[0] if extra else None
            x = (raw - self.x_mean) / self.x_std
            if self.masked:
                if present is None:
                    present = torch.ones(markers.shape[0], markers.shape[1], dtype=markers.dtype)
                x = masked_input(x, present, torch)
            z = self.nets[0](x)
            for net in self.nets[1:]:
                z = z + net(x)
            w = (z / len(self.nets)) * self.y_std + self.y_mean
            if self.has_head:
                zh = (raw - self.h_mean) / self.h_scale
                w = w + self.h_const + zh @ self.h_lin
                if self.has_quad:
                    p = zh @ self.h_dirs
                    w = w + (p[:, self.h_a] * p[:, self.h_b]) @ self.h_quad
            u = w @ self.components + self.mean
            return u.reshape(markers.shape[0], -1, 3)

    return FieldNetwork().eval()
