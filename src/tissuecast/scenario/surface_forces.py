"""The random surface force field of a sample, drawn from its seed alone.

Every sample draws, from ``numpy.random.default_rng(sample_seed)`` and in this order: the LBO
weights W (:func:`~tissuecast.forces.random_lbo_weights`), and for a test-2 sample (a
finite ``beta``) then the LSC field (:func:`~tissuecast.forces.lsc_field`, scaled to the
LBO field's nodal L2 norm), blended as ``beta f_LBO + (1 - beta) f_LSC``. The field is the
nodal forces (n, 3) N on the vertices that a data set records; the scenario applies it as
nodal forces or as a traction (:meth:`tissuecast.scenario.Scenario.sample_loads`).

The scenario's other draws (gravity, indentation) come from a stream of their own
(:func:`~tissuecast.scenario.scenario_rng`), so the fields stay those of the paper's set-up.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..config import ForceConfig
from ..forces import LBOBasis, blend, lbo_field, lsc_field, random_lbo_weights, surface_graph_laplacian
from ..mesh.tetmesh import TetMesh

__all__ = ["SurfaceForces"]


@dataclass(frozen=True, eq=False)
class SurfaceForces:
    """The random LBO (and test-2 LSC) surface force fields of a scenario's samples.

    Attributes:
        mesh: the mesh (mm).
        basis: the LBO basis (a data set stores it).
        settings: the ``[forces]`` section (LSC points, smoothing, the loading rule).
        exclude: (k,) int64 vertices no LSC force acts on (the supported vertices).
        enabled: whether the fields load the body (``scenario.lbo_forces``); without, the
            weights are still drawn (a data set records them) and the field is zero.
    """

    mesh: TetMesh
    basis: LBOBasis
    settings: ForceConfig
    exclude: np.ndarray
    enabled: bool = True

    @cached_property
    def laplacian(self):
        """The surface graph Laplacian the LSC fields are smoothed with (built on first use)."""
        return surface_graph_laplacian(self.mesh)

    def field(self, seed: int, alpha: float, beta: float = float("nan")) -> tuple[np.ndarray, np.ndarray]:
        """A sample's field from its seed (module notes).

        Args:
            seed: the sample's seed (``samples/seed`` of a data set).
            alpha: force magnitude, N.
            beta: the LBO share of a test-2 sample; NaN for an LBO sample.

        Returns:
            ``(forces (n, 3) float64 N on the vertices, weights (n_b, 3) float64)``.
        """
        rng = np.random.default_rng(np.uint64(seed))
        w = random_lbo_weights(rng, self.basis.n_vectors)
        f = lbo_field(self.basis, w, alpha, self.mesh.n_vertices)
        if not self.enabled:
            return np.zeros_like(f), w
        if not np.isnan(beta):
            s = self.settings
            f_lsc = lsc_field(self.mesh, rng, n_forces=s.lsc_points, iterations=s.lsc_iterations, rate=s.lsc_rate,
                              exclude=self.exclude, reference=f, laplacian=self.laplacian)
            f = blend(f, f_lsc, beta)
        return f, w
