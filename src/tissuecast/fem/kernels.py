"""Compiled element kernels (numba) for the neo-Hookean assembly: one fused loop per element.

:class:`~.assembly.Assembler` has two implementations of the same kernels: batched numpy
products over all elements (the reference, always available) and the loops here, compiled
by numba when it is installed (``pip install "tissuecast[fast]"``). The loops fuse what the
numpy version does in separate passes (deformation gradient, stress, element stiffness,
scatter into the CSR data), never materialise the ``(m, 30, 30)`` element matrices, build
each element stiffness from its upper block triangle, and take 3x3 determinants and inverses
by cofactors (timings in ``docs/solver.md``; ``benchmarks/dataset_throughput.py`` prints the
effect on a data set). Both give the same
numbers to round-off (``tests/fem/test_fem_kernels.py``); they differ in the last bits, so a data
set is reproducible bit for bit with the same backend (its store records the numba version).

The formulas are those of :mod:`.material` (stress and the structured tangent) and
:meth:`.assembly.Assembler._stiffness_from_factors`. Compiled code is cached on disk
(``cache=True``: the package's ``__pycache__``, else numba's user cache), so the compilation
is paid once per installation, not once per run.
"""

from __future__ import annotations

import numpy as np

try:  # optional dependency
    import numba
except ImportError:  # pragma: no cover - exercised where numba is missing
    numba = None

__all__ = ["available", "tangent", "energy_and_force", "energy"]


def available() -> bool:
    """True when numba is importable (the compiled kernels can be used)."""
    return numba is not None


if numba is not None:
    _jit = numba.njit(cache=True, nogil=True)

    @_jit
    def _kinematics(ue, g, f, h):
        """Fill F = I + u (x) grad N and H = F^-T (by cofactors) at one point; return (J, |J| guarded, I1)."""
        nn = g.shape[0]
        for i in range(3):
            for jj in range(3):
                s = 1.0 if i == jj else 0.0
                for a in range(nn):
                    s += ue[a, i] * g[a, jj]
                f[i, jj] = s
        c00 = f[1, 1] * f[2, 2] - f[1, 2] * f[2, 1]
        c01 = f[1, 2] * f[2, 0] - f[1, 0] * f[2, 2]
        c02 = f[1, 0] * f[2, 1] - f[1, 1] * f[2, 0]
        c10 = f[0, 2] * f[2, 1] - f[0, 1] * f[2, 2]
        c11 = f[0, 0] * f[2, 2] - f[0, 2] * f[2, 0]
        c12 = f[0, 1] * f[2, 0] - f[0, 0] * f[2, 1]
        c20 = f[0, 1] * f[1, 2] - f[0, 2] * f[1, 1]
        c21 = f[0, 2] * f[1, 0] - f[0, 0] * f[1, 2]
        c22 = f[0, 0] * f[1, 1] - f[0, 1] * f[1, 0]
        j = f[0, 0] * c00 + f[0, 1] * c01 + f[0, 2] * c02
        js = j if j > 0.0 else max(abs(j), 1e-12)
        h[0, 0] = c00 / js
        h[0, 1] = c01 / js
        h[0, 2] = c02 / js
        h[1, 0] = c10 / js
        h[1, 1] = c11 / js
        h[1, 2] = c12 / js
        h[2, 0] = c20 / js
        h[2, 1] = c21 / js
        h[2, 2] = c22 / js
        i1 = 0.0
        for i in range(3):
            for jj in range(3):
                i1 += f[i, jj] * f[i, jj]
        return j, js, i1

    @_jit
    def _lowest(jmin, j):
        """Running minimum of J over quadrature points; a NaN (an invalid state) sticks."""
        if jmin != jmin:
            return jmin
        return j if (j != j or j < jmin) else jmin

    @_jit
    def _stress(f, h, js, i1, mu, kappa, p):
        """First Piola-Kirchhoff stress into ``p``; returns ``(mu J^-2/3, kappa J (J - 1))``."""
        a_ = mu * js ** (-2.0 / 3.0)
        b_ = kappa * js * (js - 1.0)
        for i in range(3):
            for jj in range(3):
                p[i, jj] = a_ * (f[i, jj] - i1 / 3.0 * h[i, jj]) + b_ * h[i, jj]
        return a_, b_

    @_jit
    def _gather(u, conn, e, ue):
        for a in range(conn.shape[1]):
            n = conn[e, a]
            ue[a, 0] = u[n, 0]
            ue[a, 1] = u[n, 1]
            ue[a, 2] = u[n, 2]

    @_jit
    def _tangent(u, conn, grad, weight, mu_e, kappa_e, scatter, nnz, ndof):
        m, nq, nn, _ = grad.shape
        nd = 3 * nn
        data = np.zeros(nnz + 1)
        fint = np.zeros(ndof)
        ke = np.zeros((nd, nd))
        fe = np.zeros(nd)
        v = np.zeros(nd)
        w = np.zeros(nd)
        ue = np.zeros((nn, 3))
        f = np.zeros((3, 3))
        h = np.zeros((3, 3))
        p = np.zeros((3, 3))
        jmin = np.inf
        for e in range(m):
            mu = mu_e[e]
            kappa = kappa_e[e]
            _gather(u, conn, e, ue)
            ke[:, :] = 0.0
            fe[:] = 0.0
            for q in range(nq):
                g = grad[e, q]
                j, js, i1 = _kinematics(ue, g, f, h)
                jmin = _lowest(jmin, j)
                a_, b_ = _stress(f, h, js, i1, mu, kappa, p)
                wq = weight[e, q]
                chh = (a_ * (2.0 / 9.0) * i1 + kappa * (2.0 * js * js - js)) * wq
                ct = (a_ * i1 / 3.0 - b_) * wq
                cvw = -2.0 / 3.0 * a_ * wq
                aw = a_ * wq
                for a in range(nn):
                    for i in range(3):
                        sv = 0.0
                        sw = 0.0
                        sf = 0.0
                        for jj in range(3):
                            sv += h[i, jj] * g[a, jj]
                            sw += f[i, jj] * g[a, jj]
                            sf += p[i, jj] * g[a, jj]
                        v[3 * a + i] = sv
                        w[3 * a + i] = sw
                        fe[3 * a + i] += wq * sf
                for a in range(nn):  # upper block triangle b >= a
                    for b in range(a, nn):
                        gab = aw * (g[a, 0] * g[b, 0] + g[a, 1] * g[b, 1] + g[a, 2] * g[b, 2])
                        for i in range(3):
                            r = 3 * a + i
                            vai = v[r]
                            wai = w[r]
                            vbi = v[3 * b + i]
                            for k in range(3):
                                c = 3 * b + k
                                val = chh * vai * v[c] + ct * v[3 * a + k] * vbi + cvw * (vai * w[c] + wai * v[c])
                                if i == k:
                                    val += gab
                                ke[r, c] += val
            base = e * nd * nd
            for a in range(nn):  # lower blocks from their transposes
                for b in range(a):
                    for i in range(3):
                        for k in range(3):
                            ke[3 * a + i, 3 * b + k] = ke[3 * b + k, 3 * a + i]
            for r in range(nd):
                row = base + r * nd
                for c in range(nd):
                    data[scatter[row + c]] += ke[r, c]
            for a in range(nn):
                n = conn[e, a]
                for i in range(3):
                    fint[3 * n + i] += fe[3 * a + i]
        return fint, data[:nnz], jmin

    @_jit
    def _energy_and_force(u, conn, grad, weight, mu_e, kappa_e, c10_e, d1_e, ndof, want_force):
        m, nq, nn, _ = grad.shape
        fint = np.zeros(ndof if want_force else 0)
        ue = np.zeros((nn, 3))
        f = np.zeros((3, 3))
        h = np.zeros((3, 3))
        p = np.zeros((3, 3))
        energy = 0.0
        jmin = np.inf
        for e in range(m):
            mu = mu_e[e]
            kappa = kappa_e[e]
            c10 = c10_e[e]
            d1 = d1_e[e]
            _gather(u, conn, e, ue)
            for q in range(nq):
                g = grad[e, q]
                j, js, i1 = _kinematics(ue, g, f, h)
                jmin = _lowest(jmin, j)
                wq = weight[e, q]
                energy += wq * (c10 * (js ** (-2.0 / 3.0) * i1 - 3.0) + (js - 1.0) ** 2 / d1)
                if want_force:
                    _stress(f, h, js, i1, mu, kappa, p)
                    for i in range(3):
                        for a in range(nn):
                            fint[3 * conn[e, a] + i] += wq * (p[i, 0] * g[a, 0] + p[i, 1] * g[a, 1] + p[i, 2] * g[a, 2])
        if not jmin > 0.0:
            energy = np.inf
        return energy, fint, jmin


def _args(assembler, u):
    g = assembler.geometry
    return np.ascontiguousarray(u, dtype=np.float64), assembler.connectivity, g.grad, g.weight


def tangent(assembler, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(f_int (3 n_nodes,), K data (nnz,) in the assembler's CSR order, min J)`` at ``u`` (n_nodes, 3)."""
    mu, kappa, _, _ = assembler.element_constants
    uu, conn, grad, weight = _args(assembler, u)
    fint, data, jmin = _tangent(uu, conn, grad, weight, mu, kappa, assembler._scatter, assembler.nnz,
                                assembler.n_dofs)
    return fint, data, float(jmin)


def energy_and_force(assembler, u: np.ndarray) -> tuple[float, np.ndarray, float]:
    """``(strain energy mJ (inf if any J <= 0), f_int (3 n_nodes,) N, min J)`` at ``u``."""
    uu, conn, grad, weight = _args(assembler, u)
    e, fint, jmin = _energy_and_force(uu, conn, grad, weight, *assembler.element_constants, assembler.n_dofs, True)
    return float(e), fint, float(jmin)


def energy(assembler, u: np.ndarray) -> float:
    """Strain energy in mJ, ``inf`` if any quadrature point has J <= 0."""
    uu, conn, grad, weight = _args(assembler, u)
    e, _, _ = _energy_and_force(uu, conn, grad, weight, *assembler.element_constants, assembler.n_dofs, False)
    return float(e)
