"""Tetrahedral meshes: the :class:`TetMesh` object, file I/O and the built-in phantom."""

from .tetmesh import TET_EDGES, TET_FACES, QualityStats, TetMesh

__all__ = ["TetMesh", "QualityStats", "TET_EDGES", "TET_FACES"]
