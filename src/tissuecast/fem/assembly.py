"""Vectorised total-Lagrangian assembly of internal forces, energy and tangent stiffness.

All elements are processed at once (numpy batched products, no Python loop over elements).
The sparsity pattern of the stiffness restricted to the free degrees of freedom and the
index of every element-matrix entry in the CSR data array are computed once, when the
:class:`Assembler` is built; each assembly is then one batched kernel and one
``np.bincount``. When numba is installed the tangent, energy and internal forces run as
compiled fused loops instead (:mod:`.kernels`; same numbers to round-off, timings in
``docs/solver.md``). ``backend`` (or the environment
variable ``TISSUECAST_KERNELS=numpy|numba``) chooses.

Degrees of freedom: node ``a`` (a vertex, or for P2 a mid-edge node numbered after the
vertices), component ``i`` (x, y, z) is dof ``3 a + i``.

The material may differ per element (:class:`~.material.NeoHookeanField`), and linear springs
to ground (:class:`~.springs.NodalSprings`, an elastic support) may hold some nodes: their
energy, forces and constant stiffness are added to every evaluation (both backends), at
positions the element pattern already has (:class:`~.springs.SpringAssembly`).
"""

from __future__ import annotations

import copy
import os

import numpy as np
import scipy.sparse as sp

from ..errors import DependencyError, SolverSetupError
from . import kernels
from .elements import ElementGeometry, reference_gradients
from .material import NeoHookean, NeoHookeanField
from .springs import NodalSprings, SpringAssembly

__all__ = ["Assembler"]

#: The projected stiffness clamps the material tangent's eigenvalues to at least this share of
#: the (smallest) shear modulus.
PROJECTED_FLOOR = 1e-6


class Assembler:
    """Element kernels and scatter maps of one mesh, element order and set of free dofs.

    Args:
        nodes: (n_nodes, 3) float, mm, reference coordinates.
        connectivity: (m, nn) int, node ids of each element (nn = 4 for P1, 10 for P2).
        order: 1 or 2.
        material: the constitutive law: one :class:`~.material.NeoHookean` for every element, or
            a :class:`~.material.NeoHookeanField` with the constants of each of the m elements.
        free: (3 n_nodes,) bool, True for the unknown dofs (False: fixed or prescribed).
        rule: quadrature rule (``"default"`` or ``"high"``, see :func:`~.elements.quadrature`).
        backend: ``"numba"`` (compiled loops, :mod:`.kernels`), ``"numpy"`` (batched products)
            or ``"auto"``: ``$TISSUECAST_KERNELS`` if set, else numba when installed.
        springs: optional linear springs to ground at some nodes (N/mm); their energy, forces
            and stiffness are part of every evaluation below except :meth:`element_forces`.

    Attributes:
        backend: the kernels in use, ``"numba"`` or ``"numpy"``.
        geometry: the reference gradients and weights of every element.
        free_dofs: (n_free,) int, global ids of the free dofs; the stiffness and the
            reduced vectors are ordered like this.
        free_position: (n_dofs,) int, each global dof's position among ``free_dofs`` (-1 for
            a dof that is not free).
        element_dofs: (m, 3 nn) int, global dof ids of each element (node a, component i
            -> column 3 a + i).
        indptr, indices: CSR structure of the (n_free, n_free) stiffness (full, symmetric).
        element_constants: ``(mu, kappa, c10, d1)``, each (m,) float: the material constants of
            every element (MPa, MPa, MPa, 1/MPa).
        springs: the :class:`~.springs.SpringAssembly` of the springs, or None.
    """

    def __init__(
        self,
        nodes: np.ndarray,
        connectivity: np.ndarray,
        order: int,
        material: NeoHookean,
        free: np.ndarray,
        rule: str = "default",
        backend: str = "auto",
        springs: NodalSprings | None = None,
    ) -> None:
        self.nodes = np.asarray(nodes, dtype=np.float64)
        self.connectivity = np.asarray(connectivity, dtype=np.int64)
        self.order = int(order)
        self.material = material
        self.geometry: ElementGeometry = reference_gradients(self.nodes, self.connectivity, self.order, rule)
        m, nn = self.connectivity.shape
        self.n_nodes = len(self.nodes)
        self.n_dofs = 3 * self.n_nodes
        free = np.asarray(free, dtype=bool)
        self.free_dofs = np.flatnonzero(free)
        self.n_free = len(self.free_dofs)
        # element dof ids, layout (a, i) -> 3 a + i
        edofs = (3 * self.connectivity[:, :, None] + np.arange(3)).reshape(m, 3 * nn)
        self._edofs = edofs.ravel()
        self.element_dofs = edofs  # (m, 3 nn) global dof ids of each element, layout (a, i)
        self.free_position = np.full(self.n_dofs, -1, dtype=np.int64)
        self.free_position[self.free_dofs] = np.arange(self.n_free)
        le = self.free_position[edofs]  # (m, 3nn)
        rows = np.broadcast_to(le[:, :, None], (m, 3 * nn, 3 * nn)).ravel()
        cols = np.broadcast_to(le[:, None, :], (m, 3 * nn, 3 * nn)).ravel()
        keep = (rows >= 0) & (cols >= 0)
        key = rows[keep] * self.n_free + cols[keep]
        uniq, inverse = np.unique(key, return_inverse=True)
        self.nnz = len(uniq)
        # int32 where it fits: the compiled tangent streams this index once per assembly
        # (m * 9 nn^2 entries); half the bytes is a little of its time (docs/scaling.md)
        itype = np.int32 if self.nnz < np.iinfo(np.int32).max else np.int64
        scatter = np.full(rows.size, self.nnz, dtype=itype)  # dropped entries -> dummy bin
        scatter[keep] = inverse.ravel()
        self._scatter = scatter
        r, c = np.divmod(uniq, self.n_free)
        self.indptr = np.searchsorted(r, np.arange(self.n_free + 1)).astype(np.int64)
        self.indices = c.astype(np.int64)
        self.diagonal_index = np.flatnonzero(r == c)  # (n_free,) positions of K_ii in the data
        # CSR upper triangle == CSC lower triangle of the symmetric matrix (what CHOLMOD reads)
        upper = c >= r
        self._upper = np.flatnonzero(upper)
        self.upper_indptr = np.searchsorted(r[upper], np.arange(self.n_free + 1)).astype(np.int64)
        self.upper_indices = c[upper].astype(np.int64)
        self.backend = _backend(backend, material)
        self.element_constants = _element_constants(material, m)
        self.springs = SpringAssembly(springs, self) if springs is not None and len(springs) else None

    def with_parameters(self, material=None, springs: NodalSprings | None = None) -> "Assembler":
        """This assembler with other material constants and/or spring stiffnesses (a sample's
        drawn parameters): the mesh, quadrature, free dofs and CSR pattern are shared, so the
        tangent's symbolic factorisation stays valid.

        Args:
            material: a :class:`~.material.NeoHookean` or :class:`~.material.NeoHookeanField`
                (m elements), or None to keep this one's.
            springs: springs at the same nodes as this assembler's, or None to keep them.
        """
        out = copy.copy(self)
        if material is not None:
            out.material = material
            out.backend = _backend(self.backend, material)
            out.element_constants = _element_constants(material, len(self.connectivity))
        if springs is not None:
            if self.springs is None:
                raise SolverSetupError("with_parameters: this assembler has no springs to change")
            out.springs = self.springs.with_stiffness(springs)
        return out

    # ----------------------------------------------------------------- kinematics
    def deformation_gradient(self, u: np.ndarray) -> np.ndarray:
        """F at every quadrature point.

        Args:
            u: (n_nodes, 3) float, mm, nodal displacements.

        Returns:
            (m, q, 3, 3) float.
        """
        ue = u[self.connectivity]  # (m, nn, 3)
        f = np.matmul(ue.transpose(0, 2, 1)[:, None], self.geometry.grad)  # (m, q, 3, 3): sum_a u_ai dN_a/dX_J
        f[..., 0, 0] += 1.0
        f[..., 1, 1] += 1.0
        f[..., 2, 2] += 1.0
        return f

    # -------------------------------------------------------------------- kernels
    def energy(self, u: np.ndarray) -> float:
        """Total strain energy in mJ (N mm); ``inf`` if any quadrature point has J <= 0."""
        if self.backend == "numba":
            e = kernels.energy(self, u)
        else:
            e = float(np.sum(self.material.energy(self.deformation_gradient(u)) * self.geometry.weight))
        return e if self.springs is None else e + self.springs.energy(u)

    def energy_and_force(self, u: np.ndarray) -> tuple[float, np.ndarray, float]:
        """Strain energy and internal forces in one pass.

        Args:
            u: (n_nodes, 3) float, mm.

        Returns:
            ``(energy mJ (inf if any J <= 0), f_int (3 n_nodes,) N, min J)``.
        """
        if self.backend == "numba":
            energy, fint, jmin = kernels.energy_and_force(self, u)
        else:
            f = self.deformation_gradient(u)
            p, _, j = self.material.stress_and_tangent(f, tangent=False)
            jmin = float(j.min())
            energy = float(np.sum(self.material.energy(f) * self.geometry.weight)) if jmin > 0.0 else float("inf")
            fint = self._scatter_force(p)
        if self.springs is not None:
            energy += self.springs.energy(u)
            fint += self.springs.forces(u)
        return energy, fint, jmin

    def internal_force(self, u: np.ndarray) -> tuple[np.ndarray, float]:
        """Internal nodal forces.

        Args:
            u: (n_nodes, 3) float, mm.

        Returns:
            ``(f_int (3 n_nodes,) float N, min J over quadrature points)``.
        """
        if self.backend == "numba":
            _, fint, jmin = kernels.energy_and_force(self, u)
        else:
            f = self.deformation_gradient(u)
            p, _, j = self.material.stress_and_tangent(f, tangent=False)
            fint, jmin = self._scatter_force(p), float(j.min())
        if self.springs is not None:
            fint += self.springs.forces(u)
        return fint, jmin

    def element_forces(self, u: np.ndarray) -> np.ndarray:
        """Internal forces of every element before assembly, (m, nn, 3) N (u: (n_nodes, 3) mm);
        springs not included."""
        p, _, _ = self.material.stress_and_tangent(self.deformation_gradient(u), tangent=False)
        return self._element_force(p)

    def _element_force(self, p: np.ndarray) -> np.ndarray:
        g = self.geometry
        pw = p * g.weight[..., None, None]  # (m, q, 3, 3)
        return np.einsum("mqaJ,mqiJ->mai", g.grad, pw)  # (m, nn, 3)

    def _scatter_force(self, p: np.ndarray) -> np.ndarray:
        return np.bincount(self._edofs, weights=self._element_force(p).ravel(), minlength=self.n_dofs)

    def tangent(self, u: np.ndarray, project: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
        """Internal forces and the tangent stiffness on the free dofs.

        Args:
            u: (n_nodes, 3) float, mm.
            project: replace the material tangent at each quadrature point by its
                positive-definite part (eigenvalues clamped to ``>= 1e-6 mu``), which makes
                the stiffness positive definite (used when the true one is not).

        Returns:
            ``(f_int (3 n_nodes,) N, K data (nnz,) N/mm in the CSR order of
            ``indptr``/``indices``, min J)``.
        """
        if not project and self.backend == "numba":
            return self._with_springs(u, *kernels.tangent(self, u))
        g = self.geometry
        f = self.deformation_gradient(u)
        if not project:
            p, factors, j = self.material.stress_and_tangent(f, tangent="factors")
            ke = self._stiffness_from_factors(f, factors)
            data = np.bincount(self._scatter, weights=ke.ravel(), minlength=self.nnz + 1)[: self.nnz]
            return self._with_springs(u, self._scatter_force(p), data, float(j.min()))
        p, a, j = self.material.stress_and_tangent(f, tangent=True)
        if project:
            lam, vec = np.linalg.eigh(a)
            lam = np.maximum(lam, PROJECTED_FLOOR * float(np.min(self.material.mu)))
            a = np.matmul(vec * lam[..., None, :], np.swapaxes(vec, -1, -2))
        fint = self._scatter_force(p)
        m, q, nn, _ = g.grad.shape
        grad = g.grad.reshape(m * q, nn, 3)
        aw = (a * g.weight[..., None, None]).reshape(m * q, 27, 3)  # [(i J k), L]
        c = np.matmul(aw, grad.transpose(0, 2, 1))  # (mq, (i J k), b)
        c = c.reshape(m * q, 3, 3, 3, nn).transpose(0, 2, 1, 4, 3).reshape(m * q, 3, 9 * nn)  # [J, (i b k)]
        ke = np.matmul(grad, c).reshape(m, q, nn, 3, nn, 3).sum(axis=1)  # (m, a, i, b, k)
        data = np.bincount(self._scatter, weights=ke.ravel(), minlength=self.nnz + 1)[: self.nnz]
        return self._with_springs(u, fint, data, float(j.min()))

    def _with_springs(self, u: np.ndarray, fint: np.ndarray, data: np.ndarray, jmin: float):
        """``(f_int, K data, min J)`` with the springs' forces and stiffness added."""
        if self.springs is not None:
            fint += self.springs.forces(u)
            self.springs.add_tangent(data)
        return fint, data, jmin

    def _stiffness_from_factors(self, f: np.ndarray, factors) -> np.ndarray:
        """Element stiffnesses (m, nn, 3, nn, 3) from the structured neo-Hookean tangent.

        With ``v_ai = H_iJ dN_a/dX_J`` and ``w_ai = F_iJ dN_a/dX_J`` the quadrature-point
        stiffness is ``a (G_a . G_b) d_ik + c_hh v_ai v_bk + c_t v_ak v_bi
        - 2/3 a (v_ai w_bk + w_ai v_bk)``: a Gram matrix and rank-one products, summed over
        the quadrature points by batched matrix products (one per element).
        """
        a, c_hh, c_t, h = factors
        grad, wq = self.geometry.grad, self.geometry.weight
        m, q, nn, _ = grad.shape
        v = np.matmul(grad, np.swapaxes(h, -1, -2)).reshape(m, q, 3 * nn)  # (m, q, (a i))
        w = np.matmul(grad, np.swapaxes(f, -1, -2)).reshape(m, q, 3 * nn)
        aw, hw, tw = a * wq, c_hh * wq, c_t * wq
        cvw = (-2.0 / 3.0 * aw)[..., None]
        # c_hh v v - 2/3 a (v w + w v) as one product over 3 q terms (faster than three)
        left = np.concatenate([v * hw[..., None], v * cvw, w * cvw], axis=1)  # (m, 3q, (a i))
        right = np.concatenate([v, w, v], axis=1)
        k = np.matmul(np.swapaxes(left, 1, 2), right).reshape(m, nn, 3, nn, 3)
        vt = np.swapaxes(v, 1, 2)  # (m, (a i), q)
        k += np.matmul(vt * tw[:, None, :], v).reshape(m, nn, 3, nn, 3).transpose(0, 1, 4, 3, 2)  # c_t v_ak v_bi
        gt = grad.transpose(0, 2, 1, 3).reshape(m, nn, 3 * q)
        gram = np.matmul(gt * np.repeat(aw, 3, axis=1)[:, None, :], np.swapaxes(gt, 1, 2))  # (m, nn, nn)
        for i in range(3):
            k[:, :, i, :, i] += gram
        return k

    # ------------------------------------------------------------------- matrices
    def coupling_entries(self, local: np.ndarray) -> np.ndarray:
        """Positions (k,) int in the CSR data of the entries that couple the free-vector
        positions ``local`` ((p,) int) with other dofs (row or column in ``local``, not on
        the diagonal): zeroing them, and the residual there, holds those dofs where they are
        while keeping the pattern (and its symbolic factorisation)."""
        mark = np.zeros(self.n_free, dtype=bool)
        mark[np.asarray(local, dtype=np.int64)] = True
        rows = np.repeat(np.arange(self.n_free, dtype=np.int64), np.diff(self.indptr))
        return np.flatnonzero((mark[rows] | mark[self.indices]) & (rows != self.indices))

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The full symmetric (n_free, n_free) CSR matrix for assembled ``data``."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_free, self.n_free))

    def lower_csc(self, data: np.ndarray) -> sp.csc_matrix:
        """The lower triangle as CSC (the upper CSR triangle reinterpreted), for CHOLMOD."""
        return sp.csc_matrix(
            (data[self._upper], self.upper_indices, self.upper_indptr), shape=(self.n_free, self.n_free)
        )


def _element_constants(material, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(mu, kappa, c10, d1)``, each (m,) float64 contiguous, of a material or material field."""
    if isinstance(material, NeoHookeanField) and len(material) != m:
        raise SolverSetupError(f"the material field has {len(material)} elements, the mesh {m}")
    return tuple(np.ascontiguousarray(np.broadcast_to(np.ravel(getattr(material, k)), (m,)), dtype=np.float64)
                 for k in ("mu", "kappa", "c10", "d1"))


def _backend(choice: str, material) -> str:
    """Resolve ``Assembler(backend=...)``: "numba" or "numpy"."""
    if choice == "auto":
        choice = os.environ.get("TISSUECAST_KERNELS", "auto").strip().lower() or "auto"
    if choice not in ("auto", "numba", "numpy"):
        raise SolverSetupError(f"kernel backend must be 'auto', 'numba' or 'numpy', got {choice!r} "
                               "(argument backend or $TISSUECAST_KERNELS)")
    compiled_ok = kernels.available() and type(material) in (NeoHookean, NeoHookeanField)
    if choice == "numba" and not compiled_ok:
        raise DependencyError("kernel backend 'numba' needs numba (pip install \"tissuecast[fast]\") "
                              "and the NeoHookean material")
    if choice == "auto":
        return "numba" if compiled_ok else "numpy"
    return choice
