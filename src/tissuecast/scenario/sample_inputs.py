"""What one sample of a scenario is solved with and recorded by (:meth:`Scenario.sample`).

A sample is a pure function of its seed: its surface force field
(:class:`~.surface_forces.SurfaceForces`) and its scenario draws (:class:`ScenarioDraw`),
turned into the loads on every element node and the prescribed displacements the solver
takes. Whatever else a sample draws belongs here too, as a further field and in the draw's
record, so that the solver and the data set receive it from this one object.
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from .indentation import Indentation

__all__ = ["SampleInputs", "ScenarioDraw"]


@dataclass(frozen=True, eq=False)
class ScenarioDraw:
    """One sample's draws.

    Attributes:
        gravity_direction: (3,) unit surgery direction of gravity, or None (no gravity load).
        body_force: (3,) N/mm^3, ``rho |g| (d_surgery - d_imaging)``, or None.
        indentation: the sample's indentation, or None.
    """

    gravity_direction: np.ndarray | None = None
    body_force: np.ndarray | None = None
    indentation: Indentation | None = None

    def record(self) -> dict[str, float]:
        """Flat numbers for a data set (NaN where the load is absent): gravity direction x/y/z,
        indentation centre (vertex id), depth, slide (mm) and displacement x/y/z (mm)."""
        nan3 = [np.nan] * 3
        g = self.gravity_direction if self.gravity_direction is not None else nan3
        ind = self.indentation
        d = ind.displacement if ind is not None else nan3
        return {"gravity_x": float(g[0]), "gravity_y": float(g[1]), "gravity_z": float(g[2]),
                "indent_centre": float(ind.centre) if ind is not None else np.nan,
                "indent_depth": ind.depth if ind is not None else np.nan,
                "indent_slide": ind.slide if ind is not None else np.nan,
                "indent_x": float(d[0]), "indent_y": float(d[1]), "indent_z": float(d[2])}


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
    """

    forces: np.ndarray
    weights: np.ndarray
    surface: np.ndarray
    body: np.ndarray | None
    prescribed_ids: np.ndarray
    prescribed_values: np.ndarray
    draw: ScenarioDraw

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
