"""Decoders: the linear maps from a learned predictor's coefficients to the displacement field.

The learned predictor (:mod:`.network_predictor`) predicts coefficients w (K,) mm and a decoder
turns them into the field ``u = mean + w @ components`` (3 n,) mm, vertex-major. Two decoders
exist, chosen by ``surrogate.decoder``:

- ``"pca"``: the global PCA basis (:class:`~.pca.PCABasis`), the paper's decoder;
- ``"local"``: :class:`LocalBasis`, the global PCA basis plus local components fitted on what it
  misses. The mesh is cut into ``decoder_regions`` regions (revised k-center centres, each
  vertex to its nearest centre); in every region a PCA of the training fields' residual after
  the global projection gives orthonormal components supported on that region's vertices
  alone, and the ``decoder_components`` components of largest singular value over all regions
  are kept (most land where the global basis misses most: sharp, local features such as an
  instrument's dent or the rim of an attached face). Regions are disjoint, so the local
  components are orthonormal too, but not orthogonal to the global ones: a field's
  coefficients (:meth:`LocalBasis.transform`) are those of its least-squares projection on
  all of them (global first, then local).

Both decode with one (K, 3 n) product, so the compiled predictor, the torch and ONNX modules
and everything that reads ``components`` and ``mean`` take either unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..config import DECODERS, SurrogateConfig
from ..errors import ModelError
from .pca import PCABasis, fit_pca

__all__ = ["DECODERS", "LocalBasis", "fit_decoder", "fit_local_basis", "vertex_regions", "global_part",
           "describe_decoder"]


def vertex_regions(points: np.ndarray, count: int) -> np.ndarray:
    """Cut a mesh's vertices into ``count`` regions of nearby vertices.

    Centres by farthest-point (k-center) sampling from vertex 0, each vertex assigned to its
    nearest centre (Euclidean).

    Args:
        points: (n, 3) vertex positions, mm.
        count: number of regions, 1 <= count <= n.

    Returns:
        (n,) int64 region label of every vertex, 0..count-1 (every label used).
    """
    P = np.asarray(points, dtype=np.float64)
    if not 1 <= count <= len(P):
        raise ModelError(f"surrogate.decoder_regions must be in [1, {len(P)}] (the mesh's vertices), got {count}")
    centres = [0]
    dist = np.linalg.norm(P - P[0], axis=1)
    for _ in range(count - 1):
        c = int(dist.argmax())
        centres.append(c)
        dist = np.minimum(dist, np.linalg.norm(P - P[c], axis=1))
    D = np.linalg.norm(P[:, None, :] - P[centres][None, :, :], axis=2)
    return D.argmin(axis=1).astype(np.int64)


@dataclass(frozen=True, eq=False)
class LocalBasis:
    """The global PCA basis plus orthonormal local components of its residual.

    Attributes:
        pca: the global PCA basis (K_g components, p = 3 n features).
        local: (K_l, p) float64 orthonormal local components, each zero outside one region's
            vertices, largest singular value first.
        local_singular_values: (K_l,) their singular values on the training residual, mm.
    """

    pca: PCABasis
    local: np.ndarray
    local_singular_values: np.ndarray

    def __post_init__(self):
        if self.local.ndim != 2 or self.local.shape[1] != self.pca.n_features \
                or self.local_singular_values.shape != (self.local.shape[0],):
            raise ModelError(f"local components {self.local.shape} and singular values "
                             f"{self.local_singular_values.shape} do not fit a basis of {self.pca.n_features} "
                             "features; the model folder is inconsistent")

    @property
    def mean(self) -> np.ndarray:
        """(p,) mean training field, mm."""
        return self.pca.mean

    @cached_property
    def components(self) -> np.ndarray:
        """(K_g + K_l, p) the decoding matrix: global components, then the local ones."""
        return np.ascontiguousarray(np.vstack([self.pca.components, self.local]))

    @property
    def n_global(self) -> int:
        return self.pca.n_components

    @property
    def n_local(self) -> int:
        return int(self.local.shape[0])

    @property
    def n_components(self) -> int:
        """K = K_g + K_l coefficients."""
        return self.n_global + self.n_local

    @property
    def n_features(self) -> int:
        return self.pca.n_features

    def truncated(self, n_components: int) -> "LocalBasis":
        """The first ``n_components`` coefficients (global first, then local by singular value)."""
        if not 1 <= n_components <= self.n_components:
            raise ModelError(f"n_components must be in [1, {self.n_components}], got {n_components}")
        k = int(n_components)
        return LocalBasis(self.pca.truncated(min(k, self.n_global)), self.local[:max(k - self.n_global, 0)].copy(),
                          self.local_singular_values[:max(k - self.n_global, 0)].copy())

    @cached_property
    def _projector(self) -> np.ndarray:
        """(p, K) least-squares coefficients of a centred field: ``C^T (C C^T)^-1``."""
        C = self.components
        return np.linalg.solve(C @ C.T, C).T

    def transform(self, X) -> np.ndarray:
        """Coefficients of fields: (N, n, 3) or (N, p) mm -> (N, K) mm, those whose decoded field
        is nearest (least squares; the orthogonal projection on the decoder's span)."""
        A = np.asarray(X, dtype=np.float64).reshape(np.shape(X)[0], -1)
        if A.shape[1] != self.n_features:
            raise ModelError(f"fields have {A.shape[1]} values each, the basis expects {self.n_features}")
        return (A - self.mean) @ self._projector

    def inverse_transform(self, W) -> np.ndarray:
        """Fields from coefficients: (N, K) mm -> (N, p) mm."""
        return np.asarray(W, dtype=np.float64) @ self.components + self.mean

    def arrays(self) -> dict:
        """The local part as sparse rows (CSR) for the model folder (the global part is ``pca.npz``)."""
        rows, cols = np.nonzero(self.local)
        return {"indptr": np.r_[0, np.cumsum(np.bincount(rows, minlength=self.n_local))].astype(np.int64),
                "indices": cols.astype(np.int64), "data": self.local[rows, cols],
                "singular_values": self.local_singular_values}

    @classmethod
    def from_arrays(cls, pca: PCABasis, a: dict) -> "LocalBasis":
        """Rebuild from :meth:`arrays` and the global basis."""
        indptr, indices, data = (np.asarray(a[k]) for k in ("indptr", "indices", "data"))
        k = len(indptr) - 1
        if k < 0 or indptr[-1] != len(indices) or len(data) != len(indices) or (indices >= pca.n_features).any():
            raise ModelError("the local decoder components are inconsistent; the model folder is corrupt")
        local = np.zeros((k, pca.n_features))
        local[np.repeat(np.arange(k), np.diff(indptr)), indices] = data
        return cls(pca, local, np.asarray(a["singular_values"], dtype=np.float64))


def fit_local_basis(Ut: np.ndarray, pca: PCABasis, labels: np.ndarray, n_local: int) -> LocalBasis:
    """Fit the local components on the residual of the global basis.

    Args:
        Ut: (N, p) training fields, mm.
        pca: the global PCA basis fitted on them.
        labels: (n,) region label of every vertex (:func:`vertex_regions`).
        n_local: K_l, local components kept over all regions (fewer if the residual has fewer
            non-zero directions).

    Returns:
        The :class:`LocalBasis`.
    """
    residual = Ut - pca.inverse_transform(pca.transform(Ut))
    dofs_of, svals, vecs = [], [], []
    for r in np.unique(labels):
        dofs = (3 * np.flatnonzero(labels == r)[:, None] + np.arange(3)).ravel()
        _, s, vt = np.linalg.svd(residual[:, dofs], full_matrices=False)
        dofs_of.append(dofs)
        svals.append(s)
        vecs.append(vt)
    region = np.concatenate([np.full(len(s), i) for i, s in enumerate(svals)])
    rank = np.concatenate([np.arange(len(s)) for s in svals])
    s_all = np.concatenate(svals)
    scale = s_all.max(initial=0.0)
    order = [i for i in np.argsort(-s_all, kind="stable") if s_all[i] > 1e-10 * scale][:n_local]
    local = np.zeros((len(order), pca.n_features))
    for row, i in enumerate(order):
        local[row, dofs_of[region[i]]] = vecs[region[i]][rank[i]]
    return LocalBasis(pca, local, s_all[order].copy())


def global_part(basis: PCABasis | LocalBasis) -> PCABasis:
    """The global PCA basis of a decoder (the baselines and the trust layer's second predictor
    work in it)."""
    return basis.pca if isinstance(basis, LocalBasis) else basis


def fit_decoder(Ut: np.ndarray, n_global: int, mesh, config: SurrogateConfig) -> PCABasis | LocalBasis:
    """The decoder ``config.decoder`` names, fitted on the training fields.

    Args:
        Ut: (N, p) training fields, mm.
        n_global: K_g, components of the global PCA basis.
        mesh: the mesh of the fields (n vertices; its points cut the regions).
        config: the surrogate settings (``decoder``, ``decoder_regions``, ``decoder_components``).
    """
    pca = fit_pca(Ut, n_global)
    if config.decoder == "pca":
        return pca
    labels = vertex_regions(mesh.points, config.decoder_regions)
    return fit_local_basis(Ut, pca, labels, config.decoder_components)


def describe_decoder(basis: PCABasis | LocalBasis) -> dict:
    """A decoder's kind and coefficient counts (``model.json``, ``describe()``)."""
    if isinstance(basis, LocalBasis):
        return {"kind": "local", "global_components": basis.n_global, "local_components": basis.n_local}
    return {"kind": "pca", "global_components": int(basis.n_components), "local_components": 0}
