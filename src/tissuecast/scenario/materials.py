"""Material regions: neo-Hookean constants per element (e.g. a stiffer tumour in softer tissue).

Elements belong to regions by the mesh file's integer cell data (``materials.cell_data``,
``rule = "cell_data"``) or by distance of their centroid from a point (``rule = "distance"``);
a later region wins where two overlap; elements in no region keep the ``[material]``
section's constants. A region with ``youngs_modulus_range`` (``poisson_ratio_range``) gets
its value drawn once per data set, uniformly in the range, from the generator
:func:`material_rng` (regions in order, E before nu), so the whole data set shares it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import MaterialConfig, MaterialRegionsConfig
from ..errors import ConfigError
from ..mesh.tags import MeshTags
from ..mesh.tetmesh import TetMesh

__all__ = ["ElementMaterials", "element_materials", "material_rng", "MATERIAL_STREAM"]

#: Second SeedSequence word of the per-data-set material draws (no sample index reaches it).
MATERIAL_STREAM = 2**63 - 2


def material_rng(seed: int) -> np.random.Generator:
    """The generator of a data set's material draws: ``SeedSequence([seed, MATERIAL_STREAM])``."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), MATERIAL_STREAM]))


@dataclass(frozen=True, eq=False)
class ElementMaterials:
    """Per-element neo-Hookean constants.

    Attributes:
        youngs_modulus: (m,) float, MPa.
        poisson_ratio: (m,) float.
        region: (m,) int, index into ``names`` (-1 = the default material).
        names: region names.
        draws: {region name: {"youngs_modulus": E, "poisson_ratio": nu}} of every region
            (drawn or given).
    """

    youngs_modulus: np.ndarray
    poisson_ratio: np.ndarray
    region: np.ndarray
    names: tuple
    draws: dict

    def groups(self) -> list[tuple[float, float, np.ndarray]]:
        """``[(E, nu, element ids (k,))]``, one per distinct pair of constants, in order of first use."""
        pairs = np.column_stack([self.youngs_modulus, self.poisson_ratio])
        uniq, first, inverse = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        return [(float(uniq[k, 0]), float(uniq[k, 1]), np.flatnonzero(inverse == k)) for k in np.argsort(first)]


def element_materials(mesh: TetMesh, default: MaterialConfig, config: MaterialRegionsConfig,
                      tags: MeshTags | None = None, rng: np.random.Generator | None = None,
                      key: str = "scenario.materials") -> ElementMaterials:
    """Constants of every element (module notes).

    Args:
        mesh: the mesh (mm).
        default: the constants of elements in no region.
        config: the regions.
        tags: the mesh file's data (rule ``cell_data``).
        rng: generator of the per-data-set draws (:func:`material_rng`); None = the given
            ``youngs_modulus`` / ``poisson_ratio`` (no draw).
        key: config key for messages.

    Raises:
        ConfigError: an unknown cell-data array (the message lists those there are), or a
            region with no element.
    """
    m = mesh.n_tets
    e = np.full(m, float(default.youngs_modulus))
    nu = np.full(m, float(default.poisson_ratio))
    region = np.full(m, -1, dtype=np.int64)
    values = None
    if config.cell_data:
        data = (tags or MeshTags()).tet_data
        if config.cell_data not in data:
            have = ", ".join(repr(k) for k in sorted(data)) or "none"
            raise ConfigError(f"{key}.cell_data: the mesh has no cell data {config.cell_data!r} per tetrahedron "
                              f"(it has: {have}); set mesh.path to the file that holds it")
        values = np.asarray(data[config.cell_data])
    centroids = mesh.points[mesh.tets].mean(axis=1)
    draws = {}
    for k, reg in enumerate(config.regions):
        if reg.rule == "cell_data":
            inside = values == reg.value
            why = f"no element has {config.cell_data} = {reg.value} (values there: {np.unique(values)[:10].tolist()})"
        else:
            inside = np.linalg.norm(centroids - np.asarray(reg.point), axis=1) <= reg.distance
            why = f"no element centroid lies within {reg.distance:g} mm of {list(reg.point)}"
        if not inside.any():
            raise ConfigError(f"{key}.regions[{k}] ({reg.name!r}): {why}")
        ek = float(rng.uniform(*reg.youngs_modulus_range)) if rng is not None and reg.youngs_modulus_range \
            else reg.youngs_modulus
        nuk = float(rng.uniform(*reg.poisson_ratio_range)) if rng is not None and reg.poisson_ratio_range \
            else reg.poisson_ratio
        e[inside], nu[inside], region[inside] = ek, nuk, k
        draws[reg.name] = {"youngs_modulus": ek, "poisson_ratio": nuk}
    return ElementMaterials(e, nu, region, tuple(r.name for r in config.regions), draws)
