"""Targets: points inside the tissue where the clinic measures the error (TRE).

Surgical navigation reports its accuracy as the target registration error (TRE): the
distance between where a target (a tumour, a point of it, a planned landmark) truly is and
where the system places it, at points *inside* the tissue rather than at the worst vertex.
A :class:`Targets` object holds k such points in the mesh's frame (LPS mm) with the
tetrahedron holding each and its barycentric weights, so that any vertex field (true or
predicted displacement) is read at the targets by P1 interpolation.

Where targets come from (``[evaluate.targets]``, :func:`targets_from_config`):

``interior`` (the default)
    ``count`` interior vertices spread through the body's core: the candidates are the
    vertices at least ``depth`` mm from the outer surface (default half the deepest vertex's
    depth) and not held by a support; the first target is the deepest candidate, each next
    one the candidate farthest from the targets so far (k-center, farthest-point order; ties
    to the lowest id). Deterministic for a given mesh. A mesh without a free interior vertex
    (a thin wall) uses all its free vertices instead, from the one nearest their centroid. The
    built-in phantom is a tumour on its own (it has no regions inside), so its default targets
    are these points of its core.
``tag``
    every vertex of a named region of the mesh file (point data, point set, cell set, cell
    data; :mod:`tissuecast.mesh.tags`).
``label``
    ``count`` points of one label of a label map (e.g. the tumour inside a meshed organ): the
    centres of the label's voxels that lie inside the mesh, spread by the same farthest-point
    rule from the voxel nearest the label's centroid.
``points``
    the points of a CSV file (``x, y, z`` or ``label, x, y, z`` per row, LPS mm, a header
    line allowed) or of a 3D Slicer markups file (.mrk.json, .fcsv; RAS files converted).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, MeshError
from ..mesh.labelmap import label_map_format
from ..mesh.locate import contains_points, locate_points
from .target_files import read_target_points

__all__ = ["Targets", "interior_targets", "vertex_targets", "point_targets", "label_targets", "read_target_points",
           "targets_from_config", "check_target_source", "model_targets", "farthest_points", "DEPTH_FRACTION"]

#: Default least depth of interior targets, as a share of the deepest vertex's distance to the surface.
DEPTH_FRACTION = 0.5


@dataclass(frozen=True, eq=False)
class Targets:
    """k target points inside a mesh, ready to read vertex fields at.

    Attributes:
        name: what the targets are ("interior", a region's name, a file's name).
        description: one line for reports, e.g. "10 interior points (k-center, >= 5.2 mm deep)".
        positions: (k, 3) float, LPS mm, undeformed.
        labels: k labels (shown in Slicer next to the points).
        corners: (k, 4) int, vertex ids of the tetrahedron holding each target.
        weights: (k, 4) float, the target's barycentric coordinates in it.
    """

    name: str
    description: str
    positions: np.ndarray
    labels: tuple
    corners: np.ndarray
    weights: np.ndarray

    @property
    def count(self) -> int:
        return len(self.positions)

    def displacements(self, fields) -> np.ndarray:
        """Vertex fields (n, 3) or (B, n, 3) mm read at the targets: (k, 3) or (B, k, 3) mm.

        Raises:
            MeshError: fields of another shape, or of fewer vertices than the targets' mesh.
        """
        f = np.asarray(fields, dtype=np.float64)
        if f.ndim not in (2, 3) or f.shape[-1] != 3 or f.shape[-2] <= int(self.corners.max()):
            raise MeshError(f"target displacements need vertex fields (n, 3) or (B, n, 3) mm of the targets' mesh "
                            f"(at least {int(self.corners.max()) + 1} vertices), got shape {f.shape}")
        return np.einsum("kj,...kjd->...kd", self.weights, f[..., self.corners, :])

    def as_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "count": self.count,
                "positions_lps_mm": np.round(self.positions, 6).tolist(), "labels": list(self.labels)}


def _targets(mesh, name: str, description: str, positions, labels=()) -> Targets:
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) == 0:
        raise MeshError(f"no targets: {description}")
    loc = locate_points(mesh, positions)
    labels = tuple(labels) or tuple(f"T{i}" for i in range(len(positions)))
    return Targets(name, description, positions, labels, mesh.tets[loc.tets], loc.weights)


def farthest_points(points: np.ndarray, count: int, first: int) -> np.ndarray:
    """Farthest-point (k-center) order: ``first``, then repeatedly the point farthest from those
    chosen (ties to the lowest index). Returns (min(count, k),) int indices into ``points`` (k, 3)."""
    points = np.asarray(points, dtype=np.float64)
    chosen = [int(first)]
    gap = np.linalg.norm(points - points[first], axis=1)
    for _ in range(min(count, len(points)) - 1):
        nxt = int(np.argmax(gap))
        chosen.append(nxt)
        gap = np.minimum(gap, np.linalg.norm(points - points[nxt], axis=1))
    return np.asarray(chosen, dtype=np.int64)


def interior_targets(mesh, count: int = 10, depth: float = 0.0, exclude=()) -> Targets:
    """``count`` interior vertices spread through the core (the rule of the module docstring).

    Args:
        mesh: the tetrahedral mesh.
        count: number of targets (fewer when fewer candidates exist).
        depth: least distance from the outer surface, mm; 0 = :data:`DEPTH_FRACTION` of the
            deepest vertex's.
        exclude: vertex ids never chosen (the vertices the supports hold).
    """
    from ..markers import surface_depth

    free = np.setdiff1d(np.arange(mesh.n_vertices), np.asarray(exclude, dtype=np.int64))
    inner = np.intersect1d(mesh.interior_vertices, free)
    if inner.size == 0:  # a thin wall: every free vertex is on the surface
        if free.size == 0:
            raise MeshError("every vertex is held by a support; list target points instead (evaluate.targets.rule = "
                            "'points')")
        first = int(np.argmin(np.linalg.norm(mesh.points[free] - mesh.points[free].mean(axis=0), axis=1)))
        ids = free[farthest_points(mesh.points[free], count, first)]
        return _targets(mesh, "interior", f"{ids.size} vertices (k-center; the mesh has no free interior vertex)",
                        mesh.points[ids], [f"T{i} (vertex {v})" for i, v in enumerate(ids)])
    d = surface_depth(mesh, inner)
    least = depth if depth > 0 else DEPTH_FRACTION * float(d.max())
    keep = d >= least
    if not keep.any():
        raise MeshError(f"no interior vertex lies {least:g} mm from the surface (the deepest is {d.max():.3g} mm); "
                        "lower evaluate.targets.depth")
    cand = inner[keep]
    ids = cand[farthest_points(mesh.points[cand], count, int(np.argmax(d[keep])))]
    return _targets(mesh, "interior", f"{ids.size} interior points (k-center, >= {least:.1f} mm from the surface)",
                    mesh.points[ids], [f"T{i} (vertex {v})" for i, v in enumerate(ids)])


def vertex_targets(mesh, ids, name: str) -> Targets:
    """Every vertex of a region (0-based ids) as a target."""
    ids = np.unique(np.asarray(ids, dtype=np.int64))
    return _targets(mesh, name, f"{ids.size} vertices of region {name!r}", mesh.points[ids],
                    [f"{name} vertex {v}" for v in ids])


def point_targets(mesh, positions, labels=(), name: str = "points") -> Targets:
    """Listed points (k, 3) or (3,) LPS mm as targets; each must lie inside the mesh.

    Raises:
        MeshError: positions of another shape, or a point outside the mesh.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.shape != (3,) and (positions.ndim != 2 or positions.shape[1] != 3):
        raise MeshError(f"target points must be (k, 3) or (3,) LPS mm, got shape {positions.shape}"
                        + (" (transposed? give one row per point)" if positions.ndim == 2 and positions.shape[0] == 3 else ""))
    positions = positions.reshape(-1, 3)
    return _targets(mesh, name, f"{len(positions)} listed points ({name})", positions, labels)


def label_targets(mesh, label_map, count: int = 10, name: str = "label") -> Targets:
    """``count`` voxel centres of a label map's label (a :class:`~tissuecast.mesh.labelmap.LabelMap`)
    inside the mesh, spread by farthest-point order from the voxel nearest the label's centroid."""
    centres = label_map.to_lps(np.argwhere(label_map.mask))
    inside = contains_points(mesh, centres)
    if not inside.any():
        raise MeshError(f"no voxel of {label_map.source} lies inside the mesh; the label map and the mesh must share "
                        "the scan's frame (LPS mm)")
    pts = centres[inside]
    first = int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    order = farthest_points(pts, count, first)
    return _targets(mesh, name, f"{order.size} points of {label_map.source} ({int(inside.sum())} voxels inside the "
                    "mesh)", pts[order])


def check_target_source(config, prefix: str = "evaluate.targets.") -> None:
    """Refuse rule ``label`` when ``path`` is not a label map file (by its name).

    Args:
        config: the ``[evaluate.targets]`` section (:class:`~tissuecast.config.TargetConfig`).
        prefix: its config key with a trailing dot, for messages.

    Raises:
        ConfigError: naming ``{prefix}path`` and the file kinds rule 'label' reads.
    """
    if config.rule == "label" and config.path and label_map_format(config.path) is None:
        raise ConfigError(f"{prefix}path = {config.path!r} is not a label map; rule 'label' reads .nii, .nii.gz, "
                          ".nrrd or .seg.nrrd")


def targets_from_config(config, mesh, *, mesh_path: str = "", exclude=()) -> Targets:
    """The targets a ``[evaluate.targets]`` section (:class:`~tissuecast.config.TargetConfig`) names.

    Args:
        config: the TargetConfig.
        mesh: the model's mesh.
        mesh_path: the mesh file the model was built from (rule 'tag' reads its regions).
        exclude: vertex ids the supports hold (never interior targets).

    Raises:
        ConfigError: a ``path`` that is missing or not of the rule's kind (:func:`check_target_source`).
    """
    check_target_source(config)
    rule = config.rule
    if rule == "interior":
        return interior_targets(mesh, config.count, config.depth, exclude)
    if rule == "tag":
        from ..mesh.tags import mesh_file_tags

        return vertex_targets(mesh, mesh_file_tags(mesh_path).vertices(config.tag, config.tag_value), config.tag)
    if not Path(config.path).is_file():
        raise ConfigError(f"evaluate.targets.path = {config.path!r} does not exist")
    if rule == "label":
        from ..mesh.labelmap import read_label_map

        lm = read_label_map(config.path, label=config.label or None, segment=config.segment or None)
        return label_targets(mesh, lm, config.count, name=Path(config.path).name)
    positions, labels = read_target_points(config.path)
    return point_targets(mesh, positions, labels, name=Path(config.path).name)


def model_targets(model, config=None, *, points=None) -> Targets:
    """The targets to evaluate a model at.

    Args:
        model: a fitted DeformationModel (its mesh, its supports' vertices, its run config).
        config: a :class:`~tissuecast.config.Config` whose ``[evaluate.targets]`` and
            ``mesh.path`` apply; default the config the model was trained with (the interior
            rule when it records none).
        points: a CSV or Slicer markups file of target points (LPS mm) that replaces the
            config's targets.
    """
    from ..config import config_from_dict

    if points is not None:
        positions, labels = read_target_points(points)
        return point_targets(model.mesh, positions, labels, name=Path(points).name)
    if config is None:
        recorded = model.run_config or {}
        section = (recorded.get("evaluate") or {}).get("targets") or {}
        mesh_path = (recorded.get("mesh") or {}).get("path", "")
        config = config_from_dict({"evaluate": {"targets": section}, "mesh": {"path": mesh_path}})
    return targets_from_config(config.evaluate.targets, model.mesh, mesh_path=config.mesh.path, exclude=model.fixed)
