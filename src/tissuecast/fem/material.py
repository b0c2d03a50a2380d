"""Compressible neo-Hookean material in the Abaqus / CalculiX ``NEO HOOKE`` form.

Strain energy per reference volume (MPa = N/mm^2 = mJ/mm^3)::

    W(F) = C10 (I1_bar - 3) + (J - 1)^2 / D1,   I1_bar = J^(-2/3) tr(F^T F),   J = det F

with ``C10 = E / (4 (1 + nu))`` and ``D1 = 6 (1 - 2 nu) / E``, so that the small-strain
shear modulus is ``mu = 2 C10`` and the bulk modulus ``kappa = 2 / D1``.

With ``H = F^-T`` the first Piola-Kirchhoff stress is::

    P = mu J^(-2/3) (F - I1/3 H) + kappa J (J - 1) H

and its derivative ``A_iJkL = dP_iJ / dF_kL`` (major-symmetric) is, with ``a = mu J^(-2/3)``::

    A = a [ d_ik d_JL - 2/3 (H_iJ F_kL + F_iJ H_kL) + 2/9 I1 H_iJ H_kL + I1/3 H_iL H_kJ ]
        + kappa (2 J^2 - J) H_iJ H_kL - kappa (J^2 - J) H_iL H_kJ

Tensors are batched over leading axes; the tangent is returned as a 9x9 matrix with the
row-major flattening ``(i, J) -> 3 i + J``. :class:`NeoHookean` is one material;
:class:`NeoHookeanField` gives every element its own constants (material regions) and
evaluates the same formulas on ``(m, q, 3, 3)`` deformation gradients, one row of quadrature
points per element.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SolverSetupError

__all__ = ["NeoHookean", "NeoHookeanField"]


class _NeoHookeanLaw:
    """The NEO HOOKE formulas (module notes), written with the constants ``mu``, ``kappa``,
    ``c10`` and ``d1`` of the class that uses them (scalars, or arrays that broadcast over the
    leading axes of the deformation gradients)."""

    # ------------------------------------------------------------------ kernels
    @staticmethod
    def _invariants(f: np.ndarray):
        j = np.linalg.det(f)
        i1 = np.einsum("...ij,...ij->...", f, f)
        return j, i1

    def energy(self, f: np.ndarray) -> np.ndarray:
        """Strain energy density.

        Args:
            f: (..., 3, 3) deformation gradients.

        Returns:
            (...,) float, MPa; ``+inf`` where ``det F <= 0``.
        """
        f = np.asarray(f, dtype=np.float64)
        j, i1 = self._invariants(f)
        ok = j > 0.0
        js = np.where(ok, j, 1.0)
        w = self.c10 * (js ** (-2.0 / 3.0) * i1 - 3.0) + (js - 1.0) ** 2 / self.d1
        return np.where(ok, w, np.inf)

    def stress(self, f: np.ndarray) -> np.ndarray:
        """First Piola-Kirchhoff stress P (..., 3, 3), MPa, for deformation gradients f (..., 3, 3)."""
        return self.stress_and_tangent(f, tangent=False)[0]

    def tangent(self, f: np.ndarray) -> np.ndarray:
        """Material tangent dP/dF as (..., 9, 9), MPa, flattening (i, J) -> 3 i + J."""
        return self.stress_and_tangent(f, tangent=True)[1]

    def stress_and_tangent(self, f: np.ndarray, tangent: bool = True):
        """Stress, optional tangent, and ``det F`` in one pass.

        Args:
            f: (..., 3, 3) deformation gradients (det F > 0 expected; where it is not, the
                values are computed with |det F| and the caller must reject the state).
            tangent: also compute dP/dF; ``"factors"`` returns instead the scalars and
                ``H = F^-T`` of the closed form in the module notes, ``(a, c_hh, c_t, H)``
                with ``A = a I + c_hh H(x)H + c_t H_iL H_kJ - 2/3 a (H(x)F + F(x)H)``, which
                lets the assembler build element stiffnesses from rank-one products.

        Returns:
            ``(P (..., 3, 3) MPa, A (..., 9, 9) MPa or None, J (...,))``.
        """
        f = np.asarray(f, dtype=np.float64)
        j, i1 = self._invariants(f)
        js = np.where(j > 0.0, j, np.maximum(np.abs(j), 1e-12))
        h = np.swapaxes(np.linalg.inv(f), -1, -2)  # F^-T
        a = self.mu * js ** (-2.0 / 3.0)
        b = self.kappa * js * (js - 1.0)
        p = a[..., None, None] * (f - (i1 / 3.0)[..., None, None] * h) + b[..., None, None] * h
        if not tangent:
            return p, None, j
        shp = f.shape[:-2]
        if tangent == "factors":
            c_hh = a * (2.0 / 9.0) * i1 + self.kappa * (2.0 * js * js - js)
            return p, (a, c_hh, a * i1 / 3.0 - b, h), j
        hf = h.reshape(shp + (9,))
        ff = f.reshape(shp + (9,))
        # T_(iJ)(kL) = H_iL H_kJ
        t = np.einsum("...iL,...kJ->...iJkL", h, h).reshape(shp + (9, 9))
        hh = hf[..., :, None] * hf[..., None, :]
        hf_ff = hf[..., :, None] * ff[..., None, :]
        c_hh = a * (2.0 / 9.0) * i1 + self.kappa * (2.0 * js * js - js)
        c_t = a * i1 / 3.0 - b
        aa = (
            c_hh[..., None, None] * hh
            + c_t[..., None, None] * t
            - (2.0 / 3.0) * a[..., None, None] * (hf_ff + np.swapaxes(hf_ff, -1, -2))
        )
        aa += a[..., None, None] * np.eye(9)
        return p, aa, j


@dataclass(frozen=True)
class NeoHookean(_NeoHookeanLaw):
    """Compressible neo-Hookean solid (Abaqus/CalculiX ``*HYPERELASTIC, NEO HOOKE``).

    Args:
        youngs_modulus: small-strain Young's modulus E in MPa (21 kPa = 0.021 MPa).
        poisson_ratio: small-strain Poisson's ratio nu, in (-1, 0.5).

    Raises:
        SolverSetupError: E not positive and finite, or nu outside (-1, 0.5).
    """

    youngs_modulus: float = 0.021
    poisson_ratio: float = 0.45

    def __post_init__(self) -> None:
        e, nu = float(self.youngs_modulus), float(self.poisson_ratio)
        if not (np.isfinite(e) and e > 0.0):
            raise SolverSetupError(f"youngs_modulus must be a positive number of MPa, got {self.youngs_modulus!r}")
        if not (np.isfinite(nu) and -1.0 < nu < 0.5):
            raise SolverSetupError(
                f"poisson_ratio must lie in (-1, 0.5), got {self.poisson_ratio!r}; "
                "nu = 0.5 (incompressible) is not supported by this compressible form"
            )
        object.__setattr__(self, "youngs_modulus", e)
        object.__setattr__(self, "poisson_ratio", nu)

    @property
    def c10(self) -> float:
        """C10 = E / (4 (1 + nu)), MPa."""
        return self.youngs_modulus / (4.0 * (1.0 + self.poisson_ratio))

    @property
    def d1(self) -> float:
        """D1 = 6 (1 - 2 nu) / E, 1/MPa."""
        return 6.0 * (1.0 - 2.0 * self.poisson_ratio) / self.youngs_modulus

    @property
    def mu(self) -> float:
        """Small-strain shear modulus 2 C10, MPa."""
        return 2.0 * self.c10

    @property
    def kappa(self) -> float:
        """Small-strain bulk modulus 2 / D1, MPa."""
        return 2.0 / self.d1


def _check_constants(e: np.ndarray, nu: np.ndarray) -> None:
    if not np.all(np.isfinite(e) & (e > 0.0)):
        raise SolverSetupError("every youngs_modulus must be a positive number of MPa")
    if not np.all(np.isfinite(nu) & (nu > -1.0) & (nu < 0.5)):
        raise SolverSetupError("every poisson_ratio must lie in (-1, 0.5)")


@dataclass(frozen=True, eq=False)
class NeoHookeanField(_NeoHookeanLaw):
    """Neo-Hookean constants per element (material regions, e.g. a stiffer tumour).

    The constants ``c10``, ``d1``, ``mu`` and ``kappa`` are ``(m, 1)`` arrays, so the
    material's :meth:`energy` and :meth:`stress_and_tangent` take ``(m, q, 3, 3)`` deformation
    gradients (one row of quadrature points per element, as the assembler holds them).

    Args:
        youngs_modulus: (m,) float, MPa.
        poisson_ratio: (m,) float in (-1, 0.5).

    Raises:
        SolverSetupError: shapes differ, or a value out of range.
    """

    youngs_modulus: np.ndarray
    poisson_ratio: np.ndarray

    def __post_init__(self) -> None:
        e = np.asarray(self.youngs_modulus, dtype=np.float64).ravel()
        nu = np.asarray(self.poisson_ratio, dtype=np.float64).ravel()
        if e.shape != nu.shape or e.size == 0:
            raise SolverSetupError(f"youngs_modulus and poisson_ratio must be equally long (one per element), "
                                   f"got {e.shape} and {nu.shape}")
        _check_constants(e, nu)
        object.__setattr__(self, "youngs_modulus", e)
        object.__setattr__(self, "poisson_ratio", nu)

    def __len__(self) -> int:
        return len(self.youngs_modulus)

    @classmethod
    def uniform(cls, material: NeoHookean, n_elements: int) -> "NeoHookeanField":
        """``material`` on every one of ``n_elements`` elements."""
        return cls(np.full(n_elements, material.youngs_modulus), np.full(n_elements, material.poisson_ratio))

    def subset(self, elements: np.ndarray) -> "NeoHookeanField":
        """The constants of ``elements`` ((k,) int), in that order."""
        return NeoHookeanField(self.youngs_modulus[elements], self.poisson_ratio[elements])

    def groups(self) -> list[tuple[float, float, np.ndarray]]:
        """``[(E, nu, element ids (k,))]``, one per distinct pair of constants, in order of first use."""
        pairs = np.column_stack([self.youngs_modulus, self.poisson_ratio])
        uniq, first, inverse = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        return [(float(uniq[k, 0]), float(uniq[k, 1]), np.flatnonzero(inverse == k)) for k in np.argsort(first)]

    @property
    def c10(self) -> np.ndarray:
        """(m, 1) C10 = E / (4 (1 + nu)), MPa."""
        return (self.youngs_modulus / (4.0 * (1.0 + self.poisson_ratio)))[:, None]

    @property
    def d1(self) -> np.ndarray:
        """(m, 1) D1 = 6 (1 - 2 nu) / E, 1/MPa."""
        return (6.0 * (1.0 - 2.0 * self.poisson_ratio) / self.youngs_modulus)[:, None]

    @property
    def mu(self) -> np.ndarray:
        """(m, 1) small-strain shear modulus 2 C10, MPa."""
        return 2.0 * self.c10

    @property
    def kappa(self) -> np.ndarray:
        """(m, 1) small-strain bulk modulus 2 / D1, MPa."""
        return 2.0 / self.d1
