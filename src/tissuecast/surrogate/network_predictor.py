"""The learned predictor: PCA basis, quadratic head and network ensemble, composed.

A prediction is ``decode(head(x) + mean over members of network_k(x))``: the networks
(:class:`~.weights.MLPWeights`) and the optional quadratic head (:mod:`.head`) map the input
x = [d, a], the marker displacements d (3 n_d,) mm and the model's auxiliary inputs a (n_a,)
(:mod:`.auxiliary`: instrument poses, measured parameters; none for a markers-only model), to
the PCA weights (n_w,) mm, and the PCA basis
(:class:`~.pca.PCABasis`) decodes them into the field (3 n,) mm (with ``surrogate.decoder =
"local"`` the global basis plus local components, :mod:`.decoder`). The precompiled numpy
forward pass (:class:`~.fastpath.CompiledSurrogate`) evaluates the whole chain; the torch
module (:func:`~.network.torch_network`) is its float32 twin for ONNX.

Fitting the parts (PCA, the number of components, head, ensemble) is :mod:`.network_fit`.
"""

from __future__ import annotations

import numpy as np

from ..errors import ModelError
from .auxiliary import MARKERS_ONLY, AuxiliaryInputs
from .decoder import LocalBasis, describe_decoder
from .fastpath import CompiledSurrogate
from .field_predictor import FieldPredictor, check_vertex_ids
from .pca import PCABasis
from .quadratic import QuadraticRegression
from .weights import MLPWeights

__all__ = ["NetworkPredictor"]


class NetworkPredictor(FieldPredictor):
    """PCA + (quadratic head +) MLP ensemble surrogate of nonlinear FEM (Liu et al. 2020).

    Args:
        mesh: the :class:`~tissuecast.mesh.TetMesh` (n vertices, mm).
        markers: (n_d,) 0-based marker vertex ids, in input order.
        basis: the decoder of the n_w coefficients into fields: a PCA basis, or a
            :class:`~.decoder.LocalBasis` (``surrogate.decoder``).
        members: M >= 1 trained networks predicting the n_w weights (residual of the head).
        head: optional quadratic head (:mod:`.head`) the networks correct; None without one
            (and always None for networks trained with marker masking).
        auxiliary: the auxiliary inputs the networks and the head read after the markers
            (:class:`~.auxiliary.AuxiliaryInputs`; default none).

    Raises:
        ModelError: the parts do not fit together (components, markers, masking, inputs).
    """

    name = "mlp"

    def __init__(self, mesh, markers, basis: PCABasis | LocalBasis, members: list[MLPWeights],
                 head: QuadraticRegression | None = None, auxiliary: AuxiliaryInputs = MARKERS_ONLY):
        mk = check_vertex_ids(markers, mesh.n_vertices)
        members = list(members)
        if (not members or members[0].weights[-1].shape[0] != basis.n_components or members[0].n_markers != len(mk)
                or members[0].n_auxiliary != auxiliary.width):
            raise ModelError("network and PCA basis/markers/auxiliary inputs do not fit together; the model folder is "
                             "inconsistent")
        if head is not None and (head.coef.shape[1] != basis.n_components
                                 or head.mean.size != 3 * len(mk) + auxiliary.width or members[0].masked):
            raise ModelError("the quadratic head does not fit the network, PCA basis or markers; "
                             "the model folder is inconsistent")
        if basis.n_features != 3 * mesh.n_vertices:
            raise ModelError(f"the PCA basis describes {basis.n_features // 3} vertices, the mesh has {mesh.n_vertices}")
        self.mesh = mesh
        self.markers = mk
        self.basis = basis
        self.members = members
        self.head = head
        self.auxiliary = auxiliary
        self.compiled = CompiledSurrogate(members, basis, head)
        self._same_basis = (None, False)  # (the basis last asked about, whether it is this network's): decodes_with

    # ------------------------------------------------------------------ description
    @property
    def n_components(self) -> int:
        return self.basis.n_components

    @property
    def ensemble_size(self) -> int:
        return len(self.members)

    @property
    def hidden(self) -> tuple[int, ...]:
        """Hidden layer widths of the networks."""
        return self.members[0].hidden

    @property
    def supports_missing_markers(self) -> bool:
        """Whether the networks were trained with marker masking (``marker_dropout > 0``)."""
        return bool(self.members[0].masked)

    @property
    def has_uncertainty(self) -> bool:
        """An ensemble (>= 2 networks) gives a per-vertex spread."""
        return self.ensemble_size >= 2

    def describe(self) -> dict:
        return {**super().describe(), "n_components": self.n_components, "decoder": describe_decoder(self.basis),
                "hidden": list(self.hidden),
                "ensemble": self.ensemble_size,
                "head": None if self.head is None else {"kind": "quadratic", "dims": int(len(self.head.directions))}}

    # ------------------------------------------------------------------ prediction
    def inputs(self, d: np.ndarray, a: np.ndarray | None) -> np.ndarray:
        """The learned parts' input x (B, 3 n_d + n_a): checked displacements d (B, 3 n_d) mm and
        auxiliary inputs a (B, n_a) (every instrument present), or d itself without them."""
        if a is None:
            return d
        if self.auxiliary.absent(a).any():
            raise ModelError("this network reads the instruments' poses and cannot predict with an instrument absent "
                             "(NaN); predict with the model, whose fallback reads the markers only")
        return np.hstack([d, a])

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None, a: np.ndarray | None = None) -> np.ndarray:
        return self.compiled.fields(self.inputs(d, a), missing).reshape(d.shape[0], -1, 3)

    def decodes_with(self, basis) -> bool:
        """Whether ``basis`` (a :class:`~.pca.PCABasis`) is this network's decoder: the same
        components and mean (a trust layer fitted with the model shares them)."""
        if self._same_basis[0] is basis:
            return self._same_basis[1]
        mine = self.basis
        same = basis is mine or (isinstance(mine, PCABasis) and basis.components.shape == mine.components.shape
                                 and np.array_equal(basis.components, mine.components)
                                 and np.array_equal(basis.mean, mine.mean))
        self._same_basis = (basis, same)
        return same

    def predict_and_decode(self, d: np.ndarray, auxiliary, basis, weights) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`FieldPredictor.predict_and_decode`; with this network's own basis both are
        decoded in one product (the basis read once)."""
        if not self.decodes_with(basis):
            return super().predict_and_decode(d, auxiliary, basis, weights)
        u, v = self.compiled.fields_and_decoded(self.inputs(d, auxiliary), np.asarray(weights, dtype=np.float64))
        return u.reshape(len(d), -1, 3), v.reshape(len(d), -1, 3)

    def member_weights(self, marker_displacements, *, missing=None, auxiliary=None) -> np.ndarray:
        """PCA weights of every member (M, B, n_w) mm (the head's added), inputs as :meth:`predict` (batch)."""
        d, miss, _ = self.marker_batch(marker_displacements, missing)
        return self.compiled.member_weights(self.inputs(d, self.auxiliary_batch(auxiliary, d.shape[0])), miss)

    def predict_with_uncertainty(self, marker_displacements, *, missing=None,
                                 auxiliary=None) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble mean field and per-vertex uncertainty.

        Returns:
            ``(u, sigma)``: u (n, 3) or (B, n, 3) mm as :meth:`predict`; sigma (n,) or (B, n) mm,
            the root-mean-square over members of each vertex's deviation from the ensemble
            mean (``sqrt(sum_xyz var)``, ddof 0). Needs ``ensemble >= 2``.
        """
        d, miss, single = self.marker_batch(marker_displacements, missing)
        if not self.has_uncertainty:
            raise ModelError("uncertainty needs an ensemble; fit with surrogate.ensemble >= 2")
        W = self.compiled.member_weights(self.inputs(d, self.auxiliary_batch(auxiliary, d.shape[0])), miss)  # (M, B, n_w)
        C = self.basis.components
        u = (W.mean(axis=0) @ C + self.basis.mean).reshape(d.shape[0], -1, 3)
        dev = ((W - W.mean(axis=0)) @ C).reshape(W.shape[0], d.shape[0], -1, 3)
        sigma = np.sqrt((dev**2).sum(axis=3).mean(axis=0))
        return (u[0], sigma[0]) if single else (u, sigma)

    def pca_projection(self, fields) -> np.ndarray:
        """Projection of displacement fields on the decoder (the PCA basis, or the local one):
        (n, 3) or (B, n, 3) mm -> same shape. No prediction of this model can come closer to a
        field than this (the decoder's floor)."""
        f = np.asarray(fields, dtype=np.float64)
        flat = f.reshape(-1, self.basis.n_features)
        return self.basis.inverse_transform(self.basis.transform(flat)).reshape(f.shape)

    def torch_module(self):
        """The equivalent torch module (float32), see :func:`tissuecast.surrogate.network.torch_network`."""
        from .network import torch_network

        return torch_network(self.members, self.basis.components, self.basis.mean, self.head)

    def __repr__(self) -> str:
        return (f"NetworkPredictor(n_vertices={self.n_vertices}, markers={self.markers.tolist()}, "
                f"n_components={self.n_components}, hidden={list(self.hidden)}, ensemble={self.ensemble_size})")
