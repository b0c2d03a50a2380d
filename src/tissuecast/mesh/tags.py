"""Named regions of a mesh file (point data, point sets, cell sets, cell data) in TetMesh ids.

Multi-region meshes carry their anatomy as data next to the geometry: a point-data array
marking where the tissue is attached, an Abaqus ``*NSET``/``*ELSET``, gmsh physical groups, a
cell-data array of region numbers per tetrahedron (e.g. tumour 1, surroundings 2).
:func:`read_mesh_tags` reads them with the same vertex numbering as :func:`~.io.read_mesh`
(vertices used by no tetrahedron are dropped there, and so are they here), so that
scenario rules can name them (``tag = "posterior"``).

Ids are 0-based. The phantom and files without data have no tags (``MeshTags()``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MeshError, MeshFormatError

__all__ = ["MeshTags", "read_mesh_tags", "mesh_file_tags"]


@dataclass(frozen=True, eq=False)
class MeshTags:
    """Named regions of a mesh, in the vertex and tetrahedron ids of its :class:`TetMesh`.

    Attributes:
        point_data: name -> (n,) values per vertex (first column of multi-column arrays).
        point_sets: name -> (k,) int vertex ids.
        cell_sets: name -> (k,) int ids of the vertices of the set's cells (of any type).
        cell_data: name -> list of ``(cells (c, p) vertex ids, values (c,))`` per cell block
            (triangles, tetrahedra...); vertices the mesh dropped are -1.
        tet_data: name -> (m,) values per tetrahedron (the cell data of tetrahedron blocks).
    """

    point_data: dict = field(default_factory=dict)
    point_sets: dict = field(default_factory=dict)
    cell_sets: dict = field(default_factory=dict)
    cell_data: dict = field(default_factory=dict)
    tet_data: dict = field(default_factory=dict)

    def names(self) -> list[str]:
        """Every name a region rule can use, sorted."""
        return sorted(set(self.point_data) | set(self.point_sets) | set(self.cell_sets) | set(self.cell_data))

    def vertices(self, name: str, value: int = -1) -> np.ndarray:
        """Sorted 0-based ids of the vertices in the region ``name``.

        Args:
            name: a point-data array (vertices whose value equals ``value``, or is non-zero
                when ``value`` is -1), point set, cell set (the vertices of its cells) or
                cell-data array (the vertices of the cells with that value), looked up in
                this order.
            value: the region's value in a data array; -1 = any non-zero value.

        Raises:
            MeshError: no region of that name (the message lists the names there are).
        """
        def pick(values):
            v = np.asarray(values)
            return v != 0 if value == -1 else v == value

        if name in self.point_data:
            ids = np.flatnonzero(pick(self.point_data[name]))
        elif name in self.point_sets:
            ids = np.asarray(self.point_sets[name], dtype=np.int64)
        elif name in self.cell_sets:
            ids = np.asarray(self.cell_sets[name], dtype=np.int64)
        elif name in self.cell_data:
            ids = np.concatenate([np.asarray(c)[pick(v)].ravel() for c, v in self.cell_data[name]] or [[]])
        else:
            have = ", ".join(repr(n) for n in self.names()) or "none"
            raise MeshError(f"the mesh has no region named {name!r}; its point data, point sets, cell sets and "
                            f"cell data are: {have}")
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        return ids[ids >= 0]


def _renumber(ids, new_id: np.ndarray) -> np.ndarray:
    """File vertex ids -> mesh vertex ids (-1 where the mesh dropped the vertex)."""
    a = np.asarray(ids, dtype=np.int64)
    out = np.full(a.shape, -1, dtype=np.int64)
    ok = (a >= 0) & (a < len(new_id))
    out[ok] = new_id[a[ok]]
    return out


def mesh_file_tags(path: str | Path | None) -> MeshTags:
    """The named regions of the mesh a config or command names: :func:`read_mesh_tags` of a mesh
    file; none (empty) without a file (``None`` or ``""``: the built-in phantom) or for a label
    map (meshed from its labels, not read as a mesh file)."""
    from .labelmap import label_map_format

    if not path or label_map_format(path) is not None:
        return MeshTags()
    return read_mesh_tags(path)


def read_mesh_tags(path: str | Path) -> MeshTags:
    """The named regions of a volume mesh file, numbered like ``read_mesh(path)``'s mesh.

    Args:
        path: a mesh file of a format :func:`~.io.read_mesh` reads as a volume mesh (meshio
            formats; TetGen ``.ele`` region attributes become tet data ``"tetgen:attribute"``).
            Surface files carry no tags (they are re-meshed).

    Returns:
        The tags (empty when the file has none).

    Raises:
        MeshFormatError: missing or unreadable file.
    """
    from .io import SURFACE_FORMATS, VOLUME_FORMATS, _extension, _tets_from_meshio
    from .meshio_read import read_with_meshio

    path = Path(path)
    ext = _extension(path)
    if not path.is_file():
        raise MeshFormatError(f"mesh file '{path}' does not exist")
    if ext in SURFACE_FORMATS:
        return MeshTags()
    if ext in (".node", ".ele"):
        from .tetgen import read_tetgen

        _, tets, attributes = read_tetgen(path)
        data = {f"tetgen:attribute{'' if k == 0 else k}": attributes[:, k] for k in range(attributes.shape[1])}
        return MeshTags(tet_data=data, cell_data={k: [(tets, v)] for k, v in data.items()})
    m = read_with_meshio(path, VOLUME_FORMATS[ext])
    tets = _tets_from_meshio(m, path)
    used = np.zeros(len(m.points), dtype=bool)
    used[tets.ravel()] = True
    new_id = np.where(used, np.cumsum(used) - 1, -1)
    point_data = {str(k): (np.asarray(v)[:, 0] if np.ndim(v) == 2 else np.asarray(v))[used]
                  for k, v in m.point_data.items() if np.ndim(v) in (1, 2)}
    point_sets = {str(k): np.unique(r[r >= 0]) for k, v in m.point_sets.items() if (r := _renumber(v, new_id)).size}
    cell_sets = {}
    for name, blocks in m.cell_sets.items():
        ids = [_renumber(np.asarray(block.data)[np.asarray(sel, dtype=np.int64)], new_id).ravel()
               for block, sel in zip(m.cells, blocks) if sel is not None and len(sel)]
        ids = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
        cell_sets[str(name)] = np.unique(ids[ids >= 0])
    cell_data, tet_data = {}, {}
    is_tet = [c.type in ("tetra", "tetra4", "tetra10") for c in m.cells]
    for name, arrays in m.cell_data.items():
        pairs = [(_renumber(np.asarray(c.data), new_id), np.asarray(v).reshape(len(c.data), -1)[:, 0])
                 for c, v in zip(m.cells, arrays)]
        cell_data[str(name)] = pairs
        per_tet = [v for (_, v), t in zip(pairs, is_tet) if t]
        if per_tet and sum(len(v) for v in per_tet) == len(tets):
            tet_data[str(name)] = np.concatenate(per_tet)
    return MeshTags(point_data=point_data, point_sets=point_sets, cell_sets=cell_sets, cell_data=cell_data,
                    tet_data=tet_data)
