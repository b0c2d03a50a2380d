"""The mesh a config's ``[mesh]`` section names: the phantom, a mesh or surface file, or a label map."""

from __future__ import annotations

from .tetmesh import TetMesh

__all__ = ["mesh_from_config", "label_map_mesh_to_budget"]


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
    """
    from .io import read_mesh
    from .labelmap import label_map_format
    from .phantom import phantom

    path = mesh_config.path if path is None else path
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
