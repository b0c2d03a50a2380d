"""What one sample of a scenario is solved with and recorded by (:meth:`Scenario.sample`).

A sample is a pure function of its seed: its surface force field
(:class:`~.surface_forces.SurfaceForces`) and its scenario draws (:class:`ScenarioDraw`),
turned into the loads on every element node and the prescribed displacements the solver
takes. Whatever else a sample draws belongs here too, as a further field and in the draw's
record, so that the solver and the data set receive it from this one object.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..instruments import InstrumentPose
from .indentation import Indentation
from .parameters import ParameterDraw

__all__ = ["SampleInputs", "ScenarioDraw", "HOLD_STIFFNESS_LENGTH"]

#: mm: a vertex the reduced model's guess holds (:meth:`SampleInputs.reduced_guess`) sits on a
#: spring of this length times the nominal modulus in every direction (with E = 0.021 MPa,
#: 2.1 N/mm: ~30x a 3 mm element's own stiffness E h).
HOLD_STIFFNESS_LENGTH = 100.0


@dataclass(frozen=True, eq=False)
class ScenarioDraw:
    """One sample's draws.

    Attributes:
        gravity_direction: (3,) unit surgery direction of gravity, or None (no gravity load).
        body_force: (3,) N/mm^3, ``rho |g| (d_surgery - d_imaging)``, or None.
        indentation: the sample's indentation, or None.
        parameters: the sample's uncertain parameters (:class:`~.parameters.ParameterDraw`),
            or None when the scenario draws none.
        instruments: ``(name, pose)`` of every tracked instrument
            (:class:`~tissuecast.instruments.InstrumentPose`, from the load it is), in the order of
            ``scenario.instruments``; empty without instruments.
    """

    gravity_direction: np.ndarray | None = None
    body_force: np.ndarray | None = None
    indentation: Indentation | None = None
    parameters: ParameterDraw | None = None
    instruments: tuple[tuple[str, InstrumentPose], ...] = ()

    def record(self) -> dict[str, float]:
        """Flat numbers for a data set (NaN where the load is absent): gravity direction x/y/z,
        indentation centre (vertex id), depth, slide (mm) and displacement x/y/z (mm), the
        drawn parameters as ``param_<name>`` (with uncertain parameters) and each instrument's
        pose as ``instrument_<name>_tip_x`` ... ``_contact`` (with instruments)."""
        nan3 = [np.nan] * 3
        g = self.gravity_direction if self.gravity_direction is not None else nan3
        ind = self.indentation
        d = ind.displacement if ind is not None else nan3
        out = {"gravity_x": float(g[0]), "gravity_y": float(g[1]), "gravity_z": float(g[2]),
               "indent_centre": float(ind.centre) if ind is not None else np.nan,
               "indent_depth": ind.depth if ind is not None else np.nan,
               "indent_slide": ind.slide if ind is not None else np.nan,
               "indent_x": float(d[0]), "indent_y": float(d[1]), "indent_z": float(d[2])}
        if self.parameters is not None:
            out.update({f"param_{k}": v for k, v in self.parameters.record().items()})
        for name, pose in self.instruments:
            out.update({f"instrument_{name}_{a}_{x}": float(v) for a in ("tip", "direction")
                        for x, v in zip("xyz", getattr(pose, a))})
            out.update({f"instrument_{name}_depth": pose.depth, f"instrument_{name}_contact": float(pose.contact)})
        return out


@dataclass(frozen=True, eq=False)
class SampleInputs:
    """One sample's loads and draws.

    Attributes:
        forces: (n, 3) float64 N, the sample's surface force field on the vertices (an LBO
            field, or a test-2 blend with an LSC field; zero without LBO forces), as a data
            set records it.
        weights: (n_b, 3) float64, its LBO weights W.
        surface: (n_nodes, 3) float64 N, the field as external loads on every element node
            (nodal forces on the vertices, or the consistent loads of a traction), zero at
            the held nodes.
        body: (n_nodes, 3) float64 N, the consistent loads of the sample's gravity change, or
            None when it has none.
        prescribed_ids: (k,) int64 vertices whose displacement the sample prescribes (its
            indentation patch; k = 0 without one).
        prescribed_values: (k, 3) float64 mm, their displacements.
        draw: the sample's scenario draws (gravity direction, indentation), which a data set
            records per sample (:meth:`ScenarioDraw.record`).
        parameters: the sample's drawn uncertain parameters
            (:class:`~.parameters.ParameterDraw`; a data set records them), or None when the
            scenario draws none. Their effect is in the fields: the body loads (density), the
            prescribed ids (the attached region's extent, held at zero), and below.
        materials: (the sample's E and nu) a :class:`~tissuecast.fem.material.NeoHookeanField`
            of every element, or None for the problem's own.
        springs: the sample's :class:`~tissuecast.fem.springs.NodalSprings` (the problem's
            nodes, scaled stiffnesses), or None for the problem's own.
        extra_held: (k,) int64 vertices the sample holds at zero beyond the static supports
            (its attached region's larger extent; also among ``prescribed_ids``).
    """

    forces: np.ndarray
    weights: np.ndarray
    surface: np.ndarray
    body: np.ndarray | None
    prescribed_ids: np.ndarray
    prescribed_values: np.ndarray
    draw: ScenarioDraw
    parameters: object = None
    materials: object = None
    springs: object = None
    extra_held: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def solver_parameters(self) -> tuple:
        """``(materials, springs)`` for :meth:`tissuecast.fem.Solver.with_parameters` (both None
        for the problem's own)."""
        return self.materials, self.springs

    @property
    def held_values(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (k,) int64, values (k, 3) mm)``: the vertices the sample holds beyond the static
        supports, ascending (the indentation's patch at its prescribed values, the attached
        region's larger extent at zero)."""
        held = np.union1d(np.asarray(self.prescribed_ids, dtype=np.int64), np.asarray(self.extra_held, dtype=np.int64))
        values = np.zeros((len(held), 3))
        if len(self.prescribed_ids):
            values[np.searchsorted(held, self.prescribed_ids)] = self.prescribed_values
        return held, values

    def reduced_guess(self, reduced, hold_length: float = HOLD_STIFFNESS_LENGTH, **solve) -> np.ndarray | None:
        """The reduced model's prediction of this sample (an initial guess for the full solve):
        (n_nodes, 3) mm, or None when the reduced problem does not converge.

        ``reduced`` (:class:`~tissuecast.fem.reduced.ReducedModel`) models the nominal problem,
        loads only. The sample's prescribed vertices (an indentation's patch, a larger attached
        extent held at zero) are pulled toward their values by stiff springs
        (``hold_length`` mm, :data:`HOLD_STIFFNESS_LENGTH` by default, times the modulus, N/mm,
        with the spring's force toward the value as a load), so the guess carries the dent the
        full solve imposes; the held vertices give by their reaction over that stiffness.
        ``solve``: keywords of :meth:`~tissuecast.fem.reduced.ReducedModel.predict` (its method
        and tolerances; its defaults otherwise). With drawn parameters it predicts the sample as
        a body of the nominal E under the loads and springs over the sample's factor s on E
        (stresses scale with E: a body of E / s under loads / s on springs k / s deforms alike).
        Poisson's ratio stays the nominal model's: the full solve imposes it.
        """
        s = 1.0 if self.parameters is None else float(self.parameters.youngs_modulus)
        held, values = self.held_values
        if self.parameters is None and not len(held):
            return reduced.predict(self.loads, **solve)
        base = self.springs if self.springs is not None else reduced.problem.springs
        loads = self.loads.copy()
        np.add.at(loads, held, hold_stiffness(reduced.problem, hold_length) * values)  # their pull toward the values
        return reduced.with_springs(_guess_springs(base, held, s, reduced.problem, hold_length)).predict(loads / s, **solve)

    def solve_keywords(self) -> dict:
        """The keywords of :meth:`tissuecast.fem.Solver.solve` besides the surface loads:
        ``body_loads`` (with a gravity change) and ``prescribed`` ``(ids, values)`` (with an
        indentation); none for a sample loaded by its surface field alone."""
        out = {} if self.body is None else {"body_loads": self.body}
        if len(self.prescribed_ids):
            out["prescribed"] = (self.prescribed_ids, self.prescribed_values)
        return out

    @property
    def loads(self) -> np.ndarray:
        """(n_nodes, 3) float64 N, all external loads: the surface loads plus the body loads
        (what a reduced model predicts the solution from)."""
        return self.surface + (0.0 if self.body is None else self.body)


def _guess_springs(base, held: np.ndarray, factor: float, problem, hold_length: float):
    """The reduced guess's springs: ``base`` (NodalSprings or None) over ``factor``, plus the
    stiff hold of the ``held`` vertices (``hold_length`` mm times the modulus; also over
    ``factor``; P2: vertex ids are node ids)."""
    from ..fem.springs import NodalSprings

    nodes = np.zeros(0, dtype=np.int64) if base is None else base.nodes
    held = np.asarray(held, dtype=np.int64)
    every = np.union1d(nodes, held)
    k = np.zeros((len(every), 3, 3))
    if base is not None:
        k[np.searchsorted(every, nodes)] += base.stiffness
    if len(held):
        k[np.searchsorted(every, held)] += hold_stiffness(problem, hold_length) * np.eye(3)
    return NodalSprings(every, k / factor) if len(every) else None


def hold_stiffness(problem, length: float = HOLD_STIFFNESS_LENGTH) -> float:
    """N/mm of the springs that hold a vertex at its value in a reduced guess: ``length`` (mm)
    times the problem's mean Young's modulus."""
    return float(length) * float(np.asarray(problem.element_material.youngs_modulus).mean())
