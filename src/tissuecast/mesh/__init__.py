"""Tetrahedral meshes: the :class:`TetMesh` object, file I/O and the built-in phantom."""

from .io import read_mesh, write_mesh, write_point_set
from .phantom import phantom
from .tetmesh import TET_EDGES, TET_FACES, QualityStats, TetMesh

__all__ = ["TetMesh", "QualityStats", "TET_EDGES", "TET_FACES", "read_mesh", "write_mesh", "write_point_set", "phantom"]
