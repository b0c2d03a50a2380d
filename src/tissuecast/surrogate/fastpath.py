"""Precompiled numpy forward pass of a (possibly ensembled) surrogate: markers -> field.

Input standardisation is folded into the first layer, output scaling into the last, the PCA
reconstruction is one (n_w, 3 n) product, and the members of an ensemble are stacked (first layers
concatenated, middle layers block-diagonal, last layers averaged), so one prediction is a
handful of matmuls. A quadratic head (:mod:`.head`) adds its weights before the
reconstruction: its standardisation is folded into an affine map and a (q, 3 n_d + n_a) projection.

The folding is done in float64. The hidden layers and the decode (the basis, (n_w, 3 n), most of
the memory a frame reads) are stored and multiplied in float32 (:data:`DTYPE`, the networks' own
precision); the PCA weights (the last layer, the head) are summed in float64, so that a part that
is small beside the others (the networks' correction of the head) keeps its own relative
precision. Results are returned as float64. Where two decoded fields are compared (the trust
layer's disagreement, :meth:`CompiledSurrogate.fields_and_decoded`), the difference of their
weights is decoded, not the difference of two rounded fields.

The input is ``x = [d, a]``: the marker displacements d (3 n_d,) mm, then the model's n_a
auxiliary inputs (:mod:`.auxiliary`; none for a markers-only model), as the networks read them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag

from ..errors import ModelError
from .weights import MLPWeights, activate
from .encoding import fold_first_layer, untracked_at_mean
from .pca import PCABasis
from .quadratic import QuadraticRegression

__all__ = ["CompiledSurrogate", "DTYPE"]

#: The compiled predictor's float type (arrays stored and multiplied; results are float64).
DTYPE = np.float32


@dataclass(frozen=True, eq=False)
class _FoldedHead:
    """A quadratic head with its standardisation folded in: for inputs x (3 n_d + n_a,) the
    weights are ``const + x @ lin + (p_a p_b) @ quad`` with ``p = (x - mean) @ proj``."""

    lin: np.ndarray  # (3 n_d + n_a, n_w)
    const: np.ndarray  # (n_w,)
    mean: np.ndarray  # (3 n_d + n_a,)
    proj: np.ndarray  # (3 n_d + n_a, q)
    a: np.ndarray  # (q (q + 1) / 2,) the products' first and second directions
    b: np.ndarray
    quad: np.ndarray  # (q (q + 1) / 2, n_w)

    @classmethod
    def of(cls, head: QuadraticRegression) -> "_FoldedHead":
        n_in = head.mean.size
        coef_lin = head.coef[1:1 + n_in]
        a, b = np.triu_indices(len(head.directions))
        return cls(lin=coef_lin / head.scale[:, None], const=head.coef[0] - (head.mean / head.scale) @ coef_lin,
                   mean=head.mean.copy(), proj=(head.directions / head.scale).T.copy(), a=a, b=b,
                   quad=head.coef[1 + n_in:].copy())


class CompiledSurrogate:
    """Field predictor compiled from trained members and a PCA basis.

    Args:
        members: M >= 1 trained networks sharing input/output standardisation.
        basis: the PCA basis with n_w components matching the networks' output.
        head: optional quadratic head predicting (n_w,) weights that the networks correct
            (models without missing-marker input only).
        dtype: the float type of the hidden layers and the decode (:data:`DTYPE`; float64 gives
            the float64 forward pass, for comparisons).
    """

    def __init__(self, members: list[MLPWeights], basis: PCABasis, head: QuadraticRegression | None = None,
                 dtype=DTYPE):
        f8 = np.float64
        m0 = members[0]
        self.n_members = len(members)
        self.n_markers = m0.n_markers
        self.n_auxiliary = m0.n_auxiliary
        self.masked = m0.masked
        self.activation = m0.activation
        xm, xs = m0.x_mean.astype(f8), m0.x_std.astype(f8)
        ys, ym = m0.y_std.astype(f8), m0.y_mean.astype(f8)
        C = basis.components
        firsts, biases0, mask_cols = [], [], []
        for m in members:  # input standardisation (and present channels) folded into the first layer
            Wd, b0, present_columns = fold_first_layer(m.weights[0].astype(f8), m.biases[0].astype(f8), xm, xs, self.masked)
            if self.masked:
                mask_cols.append(present_columns)
            firsts.append(Wd)
            biases0.append(b0)
        # hidden layers as (in, out) matrices applied as h @ W + b
        self.hidden = [(np.vstack(firsts).T.copy(), np.concatenate(biases0))]
        for i in range(1, len(m0.weights) - 1):
            W = block_diag(*[m.weights[i].astype(f8) for m in members])
            b = np.concatenate([m.biases[i].astype(f8) for m in members])
            self.hidden.append((W.T.copy(), b))
        # per-member weight maps (for uncertainty) and the averaged weight map; the PCA
        # reconstruction stays a separate (n_w, p) product: folding it into the last layer
        # makes a larger matrix that is slower (memory traffic, BLAS threading) per call
        self.member_weight_maps = []
        for m in members:
            Wl = m.weights[-1].astype(f8) * ys[:, None]  # (n_w, h_last)
            bw = m.biases[-1].astype(f8) * ys + ym  # (n_w,)
            self.member_weight_maps.append((Wl.T.copy(), bw))
        self.out_W = np.vstack([W for W, _ in self.member_weight_maps]) / self.n_members  # (M h_last, n_w)
        self.out_b = np.mean([b for _, b in self.member_weight_maps], axis=0)  # (n_w,)
        self.mask_cols = np.vstack(mask_cols).T.copy() if self.masked else None  # (n_d, M h1)
        self.x_mean = xm
        self.h_last = m0.weights[-1].shape[1]
        self.head = None
        if head is not None:
            if self.masked:
                raise ModelError("a quadratic head needs every marker; models with missing-marker input have none")
            self.head = _FoldedHead.of(head)
            self.out_b = self.out_b + self.head.const
        # folded in float64 above; the hidden layers and the decode in dtype
        self.dtype = f = np.dtype(dtype)
        self.hidden = [(np.ascontiguousarray(W, dtype=f), b.astype(f)) for W, b in self.hidden]
        self.components = np.ascontiguousarray(C, dtype=f)  # (n_w, p)
        self.mean = np.asarray(basis.mean, dtype=f)  # (p,)
        self.mask_cols = None if self.mask_cols is None else self.mask_cols.astype(f)

    def _head(self, d: np.ndarray) -> np.ndarray:
        """The head's weights without its constant, (..., n_w) mm, for inputs (..., 3 n_d + n_a)."""
        f = self.head
        p = (d - f.mean) @ f.proj
        return d @ f.lin + (p[..., f.a] * p[..., f.b]) @ f.quad

    def _hidden(self, d: np.ndarray, missing: np.ndarray | None) -> np.ndarray:
        """Last hidden activations (B, M h_last) float64 for inputs (B, 3 n_d + n_a) float64
        (computed in ``dtype``)."""
        W, b = self.hidden[0]
        if missing is not None:  # missing marker -> its mean displacement and present = 0
            d = untracked_at_mean(d, missing, self.x_mean)
            b = b - missing.astype(self.dtype) @ self.mask_cols
        h = d.astype(self.dtype) @ W
        h += b
        activate(h, self.activation)
        for W, b in self.hidden[1:]:
            h = h @ W
            h += b
            activate(h, self.activation)
        return h.astype(np.float64)

    def fields(self, d: np.ndarray, missing: np.ndarray | None = None) -> np.ndarray:
        """Ensemble-mean fields (B, 3 n) float64 mm from inputs (B, 3 n_d + n_a) (marker
        displacements mm, then the auxiliary inputs).

        ``missing`` (B, n_d) bool marks untracked markers (masked models only).
        """
        if d.shape[0] == 1 and missing is None:
            return self.field(d[0])[None]
        return self._reconstruct(self._hidden(d, missing), d)

    def field(self, d: np.ndarray) -> np.ndarray:
        """One field (3 n,) float64 mm from one input vector (3 n_d + n_a,), all markers tracked.

        1-D products (BLAS gemv) keep the single-sample latency low and steady.
        """
        return self._reconstruct(self._hidden(d, None), d)

    def _weights(self, h: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ensemble-mean PCA weights (..., n_w) mm from last hidden activations (..., M h_last)
        and the input (..., 3 n_d + n_a), the head's added."""
        w = h @ self.out_W
        w += self.out_b
        if self.head is not None:
            w += self._head(d)
        return w

    def _reconstruct(self, h: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Fields (..., 3 n) float64 mm from last hidden activations (..., M h_last) and the input
        (..., 3 n_d + n_a) (decoded in ``dtype``)."""
        u = self._weights(h, d).astype(self.dtype) @ self.components
        u += self.mean
        return u.astype(np.float64)

    def fields_and_decoded(self, d: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(fields (B, 3 n), decoded (B, 3 n))`` float64 mm: :meth:`fields` of inputs (B, 3 n_d +
        n_a), every marker tracked, and other weights (B, n_w) mm decoded by the same basis, in
        one (2 B, n_w) x (n_w, 3 n) product (the basis read once). The second half decodes the
        weights' difference from the fields' (taken in float64), so ``decoded - fields`` keeps
        float32's relative precision however close the two are."""
        B = len(d)
        own = self._weights(self._hidden(d, None), d)
        w = np.empty((2 * B, self.components.shape[0]), dtype=self.dtype)
        w[:B] = own
        w[B:] = np.asarray(weights, dtype=np.float64) - own
        u = w @ self.components
        fields = u[:B]
        fields += self.mean
        fields = fields.astype(np.float64)
        return fields, fields + u[B:]

    def member_weights(self, d: np.ndarray, missing: np.ndarray | None = None) -> np.ndarray:
        """PCA weights of every member, (M, B, n_w) float64 mm (each with the head's weights added)."""
        h = self._hidden(d, missing)
        k = self.h_last
        W = np.stack([h[:, i * k:(i + 1) * k] @ W + b for i, (W, b) in enumerate(self.member_weight_maps)])
        if self.head is not None:
            W += self._head(d) + self.head.const
        return W
