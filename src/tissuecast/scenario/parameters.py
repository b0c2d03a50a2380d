"""Uncertain parameters: what the operating room does not know, drawn anew for every sample.

``[scenario.uncertain]`` gives ranges for the tissue's Young's modulus (a factor on every
element's E), its Poisson's ratio, each material region's E (a factor per region), the
density (a factor on the gravity change), the elastic support's normal and tangential
stiffness (factors) and the attached region's extent (a margin in mm along the surface: it
grows with a positive margin and shrinks with a negative one). The gravity direction is
drawn within ``scenario.gravity.cone_angle`` as before. A parameter without a range keeps
its nominal value.

Draws come from ``default_rng(SeedSequence([sample_seed, PARAMETER_STREAM]))``, a stream of
their own (the LBO field and the scenario draws of a sample stay those of a scenario without
uncertainty), one uniform number per slot in the fixed order E, nu, density, spring normal,
spring tangential, attached margin, then one per material region, whether or not the slot
has a range: giving one parameter a range does not change another's draws. Factors on
moduli and stiffnesses are log-uniform (as likely halved as doubled), the others uniform.
A parameter that ``arcsine`` names takes its number ``u`` through ``sin(pi u / 2)**2`` first:
the arcsine law (Beta(1/2, 1/2)) over its range, on the log scale for factors, its ends
likelier than its middle (:func:`law_quantile`); the other parameters' draws are unchanged.
With ``nominal_share`` > 0 one more uniform number is drawn after those: below the share, the
sample keeps every parameter at its nominal value (its other numbers unused), so the ranges'
draws of the remaining samples are those of the same seeds without the share.

How a draw acts (:class:`UncertainParameters`): the element constants and the springs of the
sample's problem, the body loads scaled by the density factor, and the attached region's
extent: the static support holds the region at its smallest extent, and the vertices of a
sample's larger extent are prescribed zero displacement in that sample's solve. The extent
is measured by the signed distance along the outer surface from the region's rim
(:func:`attached_distance`): ``-`` (distance to the nearest free surface vertex) inside the
nominal region, ``+`` (distance to the nearest attached vertex) outside; a sample with margin
``m`` holds the vertices with signed distance ``<= m``. Ids are 0-based; mm, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ..config import UncertainConfig
from ..fem.springs import NodalSprings
from ..mesh.tetmesh import TetMesh

__all__ = ["ParameterDraw", "UncertainParameters", "attached_distance", "parameter_rng", "law_quantile", "law_cdf",
           "law_sd", "PARAMETER_STREAM", "PARAMETER_NAMES", "LOG_SCALE"]

#: Second SeedSequence word of a sample's parameter draws.
PARAMETER_STREAM = 2**63 - 4
#: The per-sample parameters a data set records (``samples/param_<name>``), in draw order.
PARAMETER_NAMES = ("youngs_modulus", "poisson_ratio", "density", "spring_normal", "spring_tangential",
                   "attached_margin")
#: The parameters drawn on the log scale (factors on moduli and stiffnesses: as likely halved as doubled).
LOG_SCALE = ("youngs_modulus", "region_youngs_modulus", "spring_normal", "spring_tangential")


def parameter_rng(sample_seed) -> np.random.Generator:
    """The generator of a sample's parameter draws (module notes)."""
    return np.random.default_rng(np.random.SeedSequence([int(sample_seed), PARAMETER_STREAM]))


def attached_distance(mesh: TetMesh, attached: np.ndarray) -> np.ndarray:
    """Signed distance (mm) along the outer surface from an attached region's rim (module
    notes): (n,) float64, negative inside the region, positive outside, NaN off the surface."""
    tri = mesh.surface_triangles
    pairs = np.unique(np.sort(np.vstack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [0, 2]]]), axis=1), axis=0)
    length = np.linalg.norm(mesh.points[pairs[:, 0]] - mesh.points[pairs[:, 1]], axis=1)
    n = mesh.n_vertices
    graph = sp.coo_matrix((length, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
    inside = np.isin(surface, attached)
    out = np.full(n, np.nan)
    to_attached = dijkstra(graph, directed=False, indices=surface[inside], min_only=True)
    to_free = dijkstra(graph, directed=False, indices=surface[~inside], min_only=True)
    out[surface[~inside]] = to_attached[surface[~inside]]
    out[surface[inside]] = -to_free[surface[inside]]
    return out


@dataclass(frozen=True)
class ParameterDraw:
    """One sample's parameters (nominal where the config gives no range).

    Attributes:
        youngs_modulus: factor on every element's E.
        poisson_ratio: every element's nu, or NaN (the nominal ones).
        density: factor on the tissue density.
        spring_normal, spring_tangential: factors on the springs' stiffnesses.
        attached_margin: mm the attached region grows (+) or shrinks (-) along the surface.
        region_youngs_modulus: factor on each material region's E, in region order.
    """

    youngs_modulus: float = 1.0
    poisson_ratio: float = float("nan")
    density: float = 1.0
    spring_normal: float = 1.0
    spring_tangential: float = 1.0
    attached_margin: float = 0.0
    region_youngs_modulus: tuple[float, ...] = ()

    def record(self) -> dict[str, float]:
        """The values a data set records per sample, by :data:`PARAMETER_NAMES`."""
        return {name: float(getattr(self, name)) for name in PARAMETER_NAMES}


def law_quantile(u, arcsine: bool):
    """Where quantile ``u`` (in [0, 1]) of a parameter's law lies as a fraction of its range
    (of its log range for factors): ``u`` itself under the uniform law, ``sin(pi u / 2)**2``
    under the arcsine law."""
    return np.sin(0.5 * np.pi * np.asarray(u, dtype=np.float64)) ** 2 if arcsine else np.asarray(u, dtype=np.float64)


def law_cdf(t, arcsine: bool):
    """The law's cumulative probability at fraction ``t`` of the range (clipped to [0, 1]): the
    inverse of :func:`law_quantile`."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return 2.0 / np.pi * np.arcsin(np.sqrt(t)) if arcsine else t


def law_sd(width: float, arcsine: bool) -> float:
    """The law's standard deviation over a range ``width`` wide (on its scale): ``width /
    sqrt(12)`` uniform, ``width / sqrt(8)`` arcsine."""
    return float(width) / np.sqrt(8.0 if arcsine else 12.0)


def _value(u: float, bounds: tuple, nominal: float, log: bool) -> float:
    """The value at quantile ``u`` of a [min, max] range (log-uniform if ``log``); nominal without one."""
    if not bounds:
        return nominal
    lo, hi = float(bounds[0]), float(bounds[1])
    if log:
        return float(lo * (hi / lo) ** u)
    return float(lo + (hi - lo) * u)


@dataclass(frozen=True, eq=False)
class UncertainParameters:
    """The uncertain parameters of a scenario resolved on its mesh.

    Attributes:
        config: the ``[scenario.uncertain]`` ranges.
        youngs_modulus, poisson_ratio: (m,) float64 nominal constants of every element, MPa.
        region: (m,) int64 material region of every element (-1: none).
        n_regions: number of material regions.
        distance: (n,) float64 signed surface distance from the attached region's rim
            (:func:`attached_distance`), or None when the margin is not drawn.
        spring_parts: ``(normal (s, 3, 3), tangential (s, 3, 3))`` N/mm, the springs' normal
            and tangential stiffness matrices at the nominal stiffnesses, or None.
    """

    config: UncertainConfig
    youngs_modulus: np.ndarray
    poisson_ratio: np.ndarray
    region: np.ndarray
    n_regions: int
    distance: np.ndarray | None = None
    spring_parts: tuple | None = None

    def draw(self, rng: np.random.Generator) -> ParameterDraw:
        """A sample's parameters (module notes: one uniform number per slot, in order)."""
        u = rng.random(len(PARAMETER_NAMES) + self.n_regions)
        c = self.config
        for k, name in enumerate(PARAMETER_NAMES):
            if name in c.arcsine:
                u[k] = law_quantile(u[k], True)
        if "region_youngs_modulus" in c.arcsine:
            u[len(PARAMETER_NAMES):] = law_quantile(u[len(PARAMETER_NAMES):], True)
        nominal = {"youngs_modulus": 1.0, "poisson_ratio": float("nan"), "density": 1.0, "spring_normal": 1.0,
                   "spring_tangential": 1.0, "attached_margin": 0.0}
        values = {name: _value(u[k], getattr(c, name), nominal[name], name in LOG_SCALE)
                  for k, name in enumerate(PARAMETER_NAMES)}
        regions = tuple(_value(x, c.region_youngs_modulus, 1.0, "region_youngs_modulus" in LOG_SCALE)
                        for x in u[len(PARAMETER_NAMES):])
        if c.nominal_share and rng.random() < c.nominal_share:
            values, regions = nominal, (1.0,) * self.n_regions
        return ParameterDraw(region_youngs_modulus=regions, **values)

    def element_constants(self, draw: ParameterDraw) -> tuple[np.ndarray, np.ndarray]:
        """``(E (m,) MPa, nu (m,))`` of the sample's elements."""
        e = self.youngs_modulus * draw.youngs_modulus
        if self.n_regions:
            factors = np.append(np.asarray(draw.region_youngs_modulus, dtype=np.float64), 1.0)
            e = e * factors[self.region]  # region -1 takes the trailing 1.0
        nu = self.poisson_ratio if np.isnan(draw.poisson_ratio) else np.full_like(self.poisson_ratio,
                                                                                  draw.poisson_ratio)
        return e, nu

    def springs(self, nominal: NodalSprings | None, draw: ParameterDraw) -> NodalSprings | None:
        """The sample's springs: the nominal ones with their normal and tangential parts scaled.

        The sum is made exactly symmetric: the parts are symmetric only to the last bit, and
        where the two factors nearly cancel off the diagonal (similar factors on a stiffness
        that is about isotropic) that last bit is the whole entry."""
        if nominal is None or self.spring_parts is None:
            return nominal
        normal, tangential = self.spring_parts
        k = draw.spring_normal * normal + draw.spring_tangential * tangential
        return NodalSprings(nominal.nodes, 0.5 * (k + np.swapaxes(k, 1, 2)))

    def extra_held(self, draw: ParameterDraw, base: np.ndarray) -> np.ndarray:
        """(k,) int64 vertices the sample's attached extent holds beyond the static ``base`` ones."""
        if self.distance is None:
            return np.zeros(0, dtype=np.int64)
        held = np.flatnonzero(self.distance <= draw.attached_margin)
        return held[~np.isin(held, base)].astype(np.int64)
