"""Deck lines for a clinical scenario: springs to ground, gravity, per-element materials.

* Springs (:class:`~tissuecast.fem.springs.NodalSprings`): each node's 3x3 stiffness
  ``K_a = sum_i lambda_i q_i q_i^T`` becomes one ``SPRING1`` element per positive principal
  stiffness. An isotropic ``K_a = lambda I`` uses the global x, y, z dofs; otherwise the node
  gets ``*ORIENTATION, SYSTEM=RECTANGULAR`` (local axes ``q_1, q_2``) named on its
  ``*SPRING``. Checked with ccx 2.20: SPRING1 ignores a node's ``*TRANSFORM`` (and
  ``*TRANSFORM`` would turn the node's ``*CLOAD`` into local components) but follows the
  ``*SPRING``'s ``ORIENTATION``, and stays linear in the displacement under NLGEOM, exactly as
  the built-in solver's springs. Element ids follow the tetrahedra's.
* Gravity: ``*DENSITY`` in every material and ``*DLOAD, GRAV`` on all elements, body force
  ``density * acceleration`` (N/mm^3 with t/mm^3 and mm/s^2).
* Materials: one ``*MATERIAL`` (``NEO HOOKE``), ``*ELSET`` and ``*SOLID SECTION`` per distinct
  pair (E, nu).

Ids in the deck are 1-based (node k is row k - 1 of the element nodes, element j + 1 is
tetrahedron j).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import SolverSetupError
from ..springs import NodalSprings
from ._format import id_lines

__all__ = ["DeckScenario", "NO_ADDITIONS"]

#: Principal stiffnesses within this share of the largest count as equal (an isotropic spring).
_ISOTROPIC_RTOL = 1e-12


@dataclass(frozen=True, eq=False)
class DeckScenario:
    """What a scenario adds to a deck (see the module notes).

    Attributes:
        springs: springs to ground at element nodes, or None.
        density: t/mm^3 (needed with ``acceleration``).
        acceleration: (3,) float, mm/s^2: the body force is ``density * acceleration``; None = no
            gravity load.
        materials: ``[(E MPa, nu, element ids (k,) 0-based)]`` covering every element once, or
            None (the deck's single material everywhere).
    """

    springs: NodalSprings | None = None
    density: float | None = None
    acceleration: np.ndarray | None = None
    materials: list | None = None

    def __post_init__(self) -> None:
        if self.acceleration is not None:
            a = np.asarray(self.acceleration, dtype=np.float64).reshape(3)
            if not (self.density and self.density > 0 and np.all(np.isfinite(a))):
                raise SolverSetupError("a gravity load needs a positive density (t/mm^3) and a finite acceleration "
                                       "(3,) mm/s^2")
            object.__setattr__(self, "acceleration", a)

    @classmethod
    def from_problem(cls, problem, density: float | None = None, acceleration=None) -> "DeckScenario":
        """What a :class:`~tissuecast.fem.Problem` adds to a deck: its springs and per-element
        materials (one group per distinct (E, nu)), and a gravity load ``density * acceleration``
        if given (a problem held by pins alone, of one material and without gravity adds
        nothing: the deck's material everywhere)."""
        springs = problem.springs if problem.springs is not None and len(problem.springs) else None
        materials = problem.materials.groups() if problem.materials is not None else None
        return cls(springs=springs, density=density, acceleration=acceleration, materials=materials)

    def material_lines(self, material, n_elements: int, num) -> list[str]:
        """``*MATERIAL`` / ``*SOLID SECTION`` lines for all elements (ELSET ``TISSUE`` holds them all).

        Args:
            material: the default neo-Hookean material (``c10``, ``d1``), used when
                ``materials`` is None.
            n_elements: number of tetrahedra.
            num: the deck's number formatter.
        """
        from ..material import NeoHookean

        groups = self.materials
        if groups is None:
            groups = [(None, None, np.arange(n_elements))]
        covered = np.zeros(n_elements, dtype=np.int64)
        out = []
        for k, (e, nu, ids) in enumerate(groups):
            mat = material if e is None else NeoHookean(e, nu)
            ids = np.asarray(ids, dtype=np.int64)
            covered[ids] += 1
            name = "TISSUE" if self.materials is None else f"TISSUE{k + 1}"
            out += [f"*MATERIAL, NAME={name}", "*HYPERELASTIC, NEO HOOKE", f"{num(mat.c10)}, {num(mat.d1)}"]
            if self.acceleration is not None:
                out += ["*DENSITY", num(float(self.density))]
            if self.materials is not None:
                out += [f"*ELSET, ELSET={name}"] + id_lines(ids + 1)
            out.append(f"*SOLID SECTION, ELSET={name}, MATERIAL={name}")
        if np.any(covered != 1):
            raise SolverSetupError(f"materials must give every element exactly one material; element "
                                   f"{int(np.flatnonzero(covered != 1)[0])} has {int(covered[covered != 1][0])}")
        return out

    def spring_lines(self, first_element: int, num) -> list[str]:
        """``SPRING1`` elements (ids from ``first_element``, 1-based) and their ``*SPRING`` cards."""
        if self.springs is None or not len(self.springs):
            return []
        out: list[str] = []
        shared: dict = {}  # (dof, stiffness) -> [(element id, node)] of isotropic springs
        eid = first_element
        for node, k in zip(self.springs.nodes.tolist(), self.springs.stiffness):
            lam, q = np.linalg.eigh(k)
            top = float(lam.max())
            if top <= 0.0:
                continue
            if float(lam.max() - lam.min()) <= _ISOTROPIC_RTOL * top:
                value = float(np.mean(np.diag(k)))
                for dof in (1, 2, 3):
                    shared.setdefault((dof, value), []).append((eid, node))
                    eid += 1
                continue
            q = q[:, ::-1]  # largest first
            lam = lam[::-1]
            orient = f"OR{node + 1}"
            out += [f"*ORIENTATION, NAME={orient}, SYSTEM=RECTANGULAR",
                    ", ".join(num(float(x)) for x in np.r_[q[:, 0], q[:, 1]])]
            for dof in range(3):
                if lam[dof] <= _ISOTROPIC_RTOL * top:
                    continue
                out += [f"*ELEMENT, TYPE=SPRING1, ELSET=SP{eid}", f"{eid}, {node + 1}",
                        f"*SPRING, ELSET=SP{eid}, ORIENTATION={orient}", str(dof + 1), num(float(lam[dof]))]
                eid += 1
        for (dof, value), items in shared.items():
            name = f"SP{items[0][0]}"
            out += [f"*ELEMENT, TYPE=SPRING1, ELSET={name}"] + [f"{e}, {n + 1}" for e, n in items]
            out += [f"*SPRING, ELSET={name}", str(dof), num(value)]
        return out

    def step_lines(self, num) -> list[str]:
        """Loads of the step: ``*DLOAD, GRAV`` on every tetrahedron (ELSET ``TISSUE``)."""
        if self.acceleration is None:
            return []
        a = self.acceleration
        size = float(np.linalg.norm(a))
        if size == 0.0:
            return []
        d = a / size
        return ["*DLOAD", "TISSUE, GRAV, " + ", ".join(num(float(x)) for x in (size, *d))]


#: What a problem held by fixed vertices alone, of one material and without gravity adds to a
#: deck: nothing (the deck's material everywhere; the paper's set-up).
NO_ADDITIONS = DeckScenario()
