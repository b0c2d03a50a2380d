"""The mesh a config's ``[mesh]`` section names: the phantom, a mesh or surface file, or a label map."""

from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError
from .labelmap import label_map_format
from .mesher import SURFACE_FORMATS
from .tetmesh import TetMesh

__all__ = ["mesh_from_config", "check_mesh_source", "check_mesh_path", "label_map_mesh_to_budget"]


def check_mesh_source(mesh_config, prefix: str = "mesh.") -> None:
    """Refuse ``[mesh]`` keys that do not apply to what ``path`` names (label map, surface, volume mesh).

    Args:
        mesh_config: the ``[mesh]`` section (:class:`~tissuecast.config.MeshConfig`).
        prefix: its config key with a trailing dot, for messages.

    Raises:
        ConfigError: naming the key and the fix (``label``/``segment`` without a label map,
            ``segment`` without a segmentation, ``max_vertices`` on a mesh that is not meshed,
            ``units`` on a label map).
    """
    obj = mesh_config
    kind = label_map_format(obj.path) if obj.path else None
    if (obj.label or obj.segment) and kind is None:
        raise ConfigError(f"{prefix}label and {prefix}segment apply only when {prefix}path names a label map "
                          f"(.nii, .nii.gz, .nrrd, .seg.nrrd), got path {obj.path!r}")
    if obj.segment and kind != "segmentation":
        raise ConfigError(f"{prefix}segment names a segment of a 3D Slicer segmentation (.seg.nrrd); "
                          f"{obj.path!r} is not one: use {prefix}label")
    if obj.max_vertices and kind is None and Path(obj.path).suffix.lower() not in SURFACE_FORMATS:
        what = f"{obj.path!r} is a volume mesh, used as it is" if obj.path else "the built-in phantom is fixed"
        raise ConfigError(f"{prefix}max_vertices applies when {prefix}path names a label map or a closed surface "
                          f"(.stl .obj .ply .off .face), which are meshed; {what}: remove {prefix}max_vertices")
    if kind is not None and obj.units != "mm":
        raise ConfigError(f"{prefix}units applies to mesh files; a label map is read in its own physical units (mm), "
                          f"remove {prefix}units = {obj.units!r}")


def check_mesh_path(path: str, key: str = "mesh.path") -> None:
    """Refuse a config's mesh path that names no file, saying where a relative one is read from.

    Raises:
        ConfigError: naming ``key``, the current folder and the fix.
    """
    if path and not Path(path).exists():
        raise ConfigError(f"{key} = {path!r} does not exist: a relative path is read from the current folder "
                          f"({Path.cwd()}), not the config's; give the path from there or an absolute one")


def mesh_from_config(mesh_config, path: str | None = None) -> TetMesh:
    """Load (or build) the mesh a :class:`~tissuecast.config.MeshConfig` describes.

    Args:
        mesh_config: the ``[mesh]`` section. ``path`` empty = the built-in phantom; a label
            map (.nii, .nii.gz, .nrrd, .seg.nrrd) is meshed with ``label``/``segment``,
            ``keep_largest``, ``fill_cavities``, ``smoothing_iterations`` and
            ``surface_mesh_size`` (LPS mm, the scan's frame); any other file is read by
            :func:`tissuecast.mesh.read_mesh` (surfaces tetrahedralised at
            ``surface_mesh_size``). With ``max_vertices``, label maps and surfaces are meshed
            within that many vertices instead (:mod:`tissuecast.mesh.sizing`).
        path: use this file instead of ``mesh_config.path``.

    Returns:
        The mesh, mm, 0-based ids.

    Raises:
        ConfigError: a ``[mesh]`` key that does not apply to ``mesh_config.path``
            (:func:`check_mesh_source`), or a ``mesh.path`` that does not exist (neither asked
            when ``path`` replaces it).
    """
    from .io import read_mesh
    from .phantom import phantom

    if path is None:
        check_mesh_source(mesh_config)
        path = mesh_config.path
        check_mesh_path(path)
    if not path:
        return phantom()
    if label_map_format(path) is not None:
        if mesh_config.max_vertices:
            return label_map_mesh_to_budget(path, mesh_config)
        from .from_image import mesh_from_image

        return mesh_from_image(
            path,
            mesh_config.surface_mesh_size,
            label=mesh_config.label or None,
            segment=mesh_config.segment or None,
            keep_largest=mesh_config.keep_largest,
            fill_cavities=mesh_config.fill_cavities,
            smoothing_iterations=mesh_config.smoothing_iterations,
        )
    return read_mesh(path, units=mesh_config.units, mesh_size=mesh_config.surface_mesh_size,
                     max_vertices=mesh_config.max_vertices or None)


def label_map_mesh_to_budget(path: str, mesh_config) -> TetMesh:
    """A label map meshed within ``mesh_config.max_vertices`` vertices (label, segment, pieces,
    cavities and smoothing as the config says; :func:`~tissuecast.mesh.sizing.mesh_label_map_to_budget`)."""
    from .from_image import label_pieces
    from .labelmap import LabelMap, read_label_map
    from .sizing import mesh_label_map_to_budget

    labelmap = read_label_map(path, label=mesh_config.label or None, segment=mesh_config.segment or None)
    mask = label_pieces(labelmap.mask, keep_largest=mesh_config.keep_largest, fill_cavities=mesh_config.fill_cavities,
                        source=labelmap.source)
    piece = LabelMap(mask, labelmap.ijk_to_lps, labelmap.source)
    return mesh_label_map_to_budget(piece, mesh_config.max_vertices,
                                    smoothing_iterations=mesh_config.smoothing_iterations).mesh
