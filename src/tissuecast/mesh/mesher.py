"""Closed triangulated surface -> tetrahedral mesh, with gmsh.

Used by :func:`tissuecast.mesh.read_mesh` for surface files (.stl .obj .ply .off, TetGen
.face) and by ``scripts/make_phantom.py``. The surface must be a closed, manifold triangle
mesh; it is re-meshed at the requested size (mm) and the enclosed volume filled with
tetrahedra (gmsh Delaunay + Netgen optimisation). gmsh runs in a fresh child process with its
own threads and those of the BLAS linked into it pinned to one (:data:`GMSH_ENVIRONMENT`), so
that the mesh does not depend on the machine's core count or the caller's thread settings;
another CPU or gmsh version may still give another mesh (callers that need one mesh ship it).
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import MeshError, require
from .tetmesh import TetMesh

__all__ = ["SURFACE_FORMATS", "merge_duplicate_points", "check_closed_surface", "orient_surface", "tetrahedralize_surface"]

log = logging.getLogger(__name__)

#: closed-surface file extensions (tetrahedralised on reading) and their meshio format names
SURFACE_FORMATS = {".stl": "stl", ".obj": "obj", ".ply": "ply", ".off": "off", ".face": "tetgen"}
_REPAIR = ("it must be a closed manifold surface (watertight, every edge shared by exactly two triangles); "
           "repair it (e.g. MeshLab, PyMeshFix) first")
#: A triangle smaller than this share of the largest one's area counts as zero-area (degenerate).
_ZERO_AREA_SHARE = 1e-12
#: gmsh may shrink elements down to this share of the target size where the surface needs it.
MIN_SIZE_SHARE = 0.5
#: gmsh algorithms: 2D Frontal-Delaunay (6) for the re-meshed surface, 3D Delaunay (1) inside.
GMSH_ALGORITHM_2D = 6
GMSH_ALGORITHM_3D = 1
#: The meshing child's environment: gmsh's wheel links its own OpenBLAS, which reads its thread
#: count from these when the library loads. Its threaded kernels round differently, and gmsh's
#: re-parametrisation of the surface turns that rounding into another mesh, so the child pins it
#: to one thread: the same mesh whatever the machine's core count or the caller's settings.
GMSH_ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "GOTO_NUM_THREADS": "1"}
#: The suffix the meshing child gives its answer file's name for gmsh's error message instead.
CHILD_ERROR_SUFFIX = ".error"


def start_gmsh(gmsh) -> None:
    """``gmsh.initialize()``, then give SIGPIPE back to Python.

    gmsh's initialisation resets SIGPIPE to the system default, which makes any later write
    to a closed pipe kill the whole process instead of raising ``BrokenPipeError`` (Python
    ignores SIGPIPE); e.g. a data-set run whose worker process died would vanish without its
    clear error. We restore Python's setting (main thread only; no SIGPIPE on Windows).
    """
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    if hasattr(signal, "SIGPIPE") and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)


def merge_duplicate_points(points: np.ndarray, triangles: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident vertices (STL files store each triangle's corners separately).

    Args:
        points: (n, 3) float, mm.
        triangles: (k, 3) int, 0-based.
        tol: merge distance relative to the bounding-box diagonal.

    Returns:
        (points (n', 3) float mm, triangles (k, 3) int) without duplicate or unused vertices.
    """
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    diag = float(np.linalg.norm(points.max(0) - points.min(0))) or 1.0
    key = np.round(points / (tol * diag)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    tri = inverse.ravel()[triangles]
    used = np.unique(tri)
    renum = np.full(len(first), -1, dtype=np.int64)
    renum[used] = np.arange(len(used))
    return points[first[used]], renum[tri]


def check_closed_surface(points: np.ndarray, triangles: np.ndarray) -> None:
    """Raise :class:`MeshError` unless the triangles form a closed manifold surface.

    Closed: every edge belongs to exactly two triangles. Manifold: no edge belongs to more
    than two triangles and the triangles around every vertex form one fan. Degenerate
    (zero-area) triangles are refused too.

    Args:
        points: (n, 3) float, mm.
        triangles: (k, 3) int, 0-based, without duplicate vertices (see
            :func:`merge_duplicate_points`).
    """
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) < 4:
        raise MeshError(f"a surface needs at least 4 triangles, got {len(tri)}; {_REPAIR}")
    if ((tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])).any():
        raise MeshError(f"the surface has triangles with a repeated vertex; {_REPAIR}")
    p = np.asarray(points, dtype=np.float64)[tri]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    if (area <= _ZERO_AREA_SHARE * area.max()).any():
        raise MeshError(f"the surface has {int((area <= _ZERO_AREA_SHARE * area.max()).sum())} zero-area triangles; {_REPAIR}")
    _check_edges(tri)
    _check_vertex_fans(tri)


def _check_edges(tri: np.ndarray) -> None:
    """Every edge shared by exactly two triangles (closed, edge-manifold)."""
    edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    if (counts == 1).any():
        raise MeshError(
            f"the surface is open: {int((counts == 1).sum())} edges belong to only one triangle (holes); {_REPAIR}"
        )
    if (counts > 2).any():
        raise MeshError(
            f"the surface is non-manifold: {int((counts > 2).sum())} edges are shared by more than two triangles; {_REPAIR}"
        )


def _check_vertex_fans(tri: np.ndarray) -> None:
    """The triangles around every vertex form one fan (no two sheets touching at a vertex)."""
    # corners (triangle, vertex) joined across shared edges form one fan per vertex on a
    # manifold surface; two fans touching at a vertex give two groups.
    loc = np.array([[0, 1], [1, 2], [2, 0]])
    ends = tri[:, loc]  # (k, 3, 2) vertex ids of the half-edges
    corners = (3 * np.arange(len(tri))[:, None, None] + loc[None]).reshape(-1, 2)
    ends = ends.reshape(-1, 2)
    swap = ends[:, 0] > ends[:, 1]
    corners[swap] = corners[swap][:, ::-1]  # corner at the smaller vertex id first
    key = np.sort(ends, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    first, second = corners[order[0::2]], corners[order[1::2]]
    g = sp.coo_matrix(
        (np.ones(2 * len(first)), (np.r_[first[:, 0], first[:, 1]], np.r_[second[:, 0], second[:, 1]])),
        shape=(3 * len(tri), 3 * len(tri)),
    )
    n_fans, labels = connected_components(g, directed=False)
    n_vertices = len(np.unique(tri))
    if n_fans != n_vertices:
        fans = np.bincount(np.unique(np.c_[labels, tri.ravel()], axis=0)[:, 1])
        bad = np.flatnonzero(fans > 1)
        raise MeshError(
            f"the surface is non-manifold at {len(bad)} vertices where separate sheets touch "
            f"(first: vertex {int(bad[0])}); {_REPAIR}"
        )


def orient_surface(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Re-order triangle vertices so that all normals point outward (STL files often mix them).

    Args:
        points: (n, 3) float, mm.
        triangles: (k, 3) int, a closed manifold surface (see :func:`check_closed_surface`).

    Returns:
        (k, 3) int: the triangles, some with two vertices swapped, consistently oriented
        with a positive enclosed volume.
    """
    tri = np.array(triangles, dtype=np.int64)
    k = len(tri)
    half = tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(half, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    h1, h2 = order[0::2], order[1::2]  # the two half-edges of every edge
    t1, t2 = h1 // 3, h2 // 3
    agree = half[h1, 0] == half[h2, 1]  # neighbours traverse the shared edge in opposite directions
    # graph on (triangle, kept) and (triangle, flipped) states; agreeing neighbours link same states
    rows = np.r_[t1, t1 + k]
    cols = np.r_[np.where(agree, t2, t2 + k), np.where(agree, t2 + k, t2)]
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * k, 2 * k))
    _, labels = connected_components(graph, directed=False)
    if (labels[:k] == labels[k:]).any():
        raise MeshError("the surface is not orientable; it must be a closed manifold surface enclosing a volume")
    flip = labels[:k] > labels[k:]
    tri[flip] = tri[flip][:, [0, 2, 1]]
    p = np.asarray(points, dtype=np.float64)[tri]
    if np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() < 0:
        tri = tri[:, [0, 2, 1]]
    return tri


# gmsh can hang on bad input (seen for > 10 minutes, deaf to SIGTERM, on a raw lung surface):
# meshing runs in a child process that is killed past this many seconds.
MESH_TIMEOUT_S = 900.0


def run_gmsh(gmsh, points, triangles, *, mesh_size, interior_size, optimize, feature_angle, curvature_points):
    """gmsh's surface re-meshing and volume meshing in this process (the meshing child's work,
    :mod:`.gmsh_child`; the options as :func:`tetrahedralize_surface`'s).

    Args:
        gmsh: the gmsh module (initialised here, and finalised, unless the caller has done so).
        points: (n, 3) float64 mm; triangles: (k, 3) int64, 0-based, a closed oriented surface.

    Returns:
        ``(node tags (p,), coordinates (3 p,) mm, tetrahedra's node tags (4 m,))`` as gmsh gives them.
    """
    started = gmsh.isInitialized()
    if not started:
        start_gmsh(gmsh)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 1)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("tissuecast-surface")
        surf = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surf, np.arange(1, len(points) + 1), points.ravel())
        gmsh.model.mesh.addElementsByType(surf, 2, [], (triangles + 1).ravel())
        gmsh.model.mesh.classifySurfaces(math.radians(feature_angle), True, True, math.pi)
        gmsh.model.mesh.createGeometry()
        loop = gmsh.model.geo.addSurfaceLoop([e[1] for e in gmsh.model.getEntities(2)])
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        for name, value in [
            ("Mesh.MeshSizeMin", MIN_SIZE_SHARE * mesh_size),
            ("Mesh.MeshSizeMax", mesh_size),
            ("Mesh.MeshSizeFromCurvature", int(curvature_points)),
            ("Mesh.MeshSizeExtendFromBoundary", 1),
            ("Mesh.Algorithm", GMSH_ALGORITHM_2D),
            ("Mesh.Algorithm3D", GMSH_ALGORITHM_3D),
            ("Mesh.Optimize", int(optimize)),
            ("Mesh.OptimizeNetgen", int(optimize)),
            ("Mesh.RandomSeed", 1),
        ]:
            gmsh.option.setNumber(name, value)
        if interior_size is not None:
            const = gmsh.model.mesh.field.add("Constant")
            gmsh.model.mesh.field.setNumber(const, "VIn", float(interior_size))
            gmsh.model.mesh.field.setNumbers(const, "VolumesList", [e[1] for e in gmsh.model.getEntities(3)])
            gmsh.model.mesh.field.setNumber(const, "IncludeBoundary", 0)
            gmsh.model.mesh.field.setAsBackgroundMesh(const)
            gmsh.option.setNumber("Mesh.MeshSizeMin", MIN_SIZE_SHARE * min(mesh_size, interior_size))
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
    except Exception as exc:  # gmsh raises plain Exception with its own message
        raise MeshError(f"gmsh could not tetrahedralise the surface ({exc}); check that it is a closed manifold surface") from exc
    finally:
        if not started:
            gmsh.finalize()
        else:  # the caller runs gmsh: leave its other models alone
            gmsh.model.remove()
    return np.asarray(tags), np.asarray(coords), np.asarray(tet_nodes)


def _gmsh_in_child(points, triangles, options: dict, timeout: float):
    """:func:`run_gmsh` in a fresh Python process (:mod:`.gmsh_child`) started with
    :data:`GMSH_ENVIRONMENT`, killed after ``timeout`` seconds."""
    with tempfile.TemporaryDirectory(prefix="tissuecast-gmsh-") as tmp:
        job, out = Path(tmp) / "surface.npz", Path(tmp) / "mesh.npz"
        np.savez(job, points=np.asarray(points, dtype=np.float64), triangles=np.asarray(triangles, dtype=np.int64),
                 options=json.dumps(options))
        child = subprocess.Popen([sys.executable, "-m", "tissuecast.mesh.gmsh_child", str(job), str(out)],
                                 env=_child_environment(), stdin=subprocess.DEVNULL,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            _, err = child.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise MeshError(
                f"gmsh did not finish meshing within {timeout:.0f} s and was stopped; the surface is probably "
                "too complex or self-touching for its re-meshing: try a larger mesh size, a smoother or cleaner "
                "surface, or a longer timeout") from None
        finally:  # stopped past the timeout, or the caller interrupted: no gmsh is left running
            if child.poll() is None:
                child.kill()
                child.communicate()
        if out.with_suffix(CHILD_ERROR_SUFFIX).exists():
            raise MeshError(out.with_suffix(CHILD_ERROR_SUFFIX).read_text())
        if child.returncode != 0 or not out.exists():
            last = err.strip().splitlines()[-1] if err.strip() else "no message"
            raise MeshError(f"gmsh crashed while meshing (exit code {child.returncode}: {last}); check that the "
                            "surface is a clean closed manifold, or try another mesh size")
        with np.load(out, allow_pickle=False) as z:
            return z["tags"], z["coords"], z["tet_nodes"]


def _child_environment() -> dict:
    """The meshing child's environment: the caller's, :data:`GMSH_ENVIRONMENT`, and the folders
    this tissuecast and gmsh were imported from first on ``PYTHONPATH`` (the child imports the
    same ones, also where the caller found them through ``sys.path``)."""
    import gmsh

    own = [str(Path(__file__).resolve().parents[2]), str(Path(gmsh.__file__).resolve().parent)]
    path = os.pathsep.join(dict.fromkeys(own + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    return {**os.environ, **GMSH_ENVIRONMENT, "PYTHONPATH": path}


def _check_options(mesh_size, timeout) -> None:
    if not (isinstance(mesh_size, (int, float)) and math.isfinite(mesh_size) and mesh_size > 0):
        raise MeshError(f"mesh_size must be a positive length in mm, got {mesh_size!r}")
    if not (isinstance(timeout, (int, float)) and timeout > 0):
        raise MeshError(f"timeout must be a positive number of seconds, got {timeout!r}")


def _tet_mesh(tags: np.ndarray, coords: np.ndarray, tet_nodes: np.ndarray) -> TetMesh:
    """The TetMesh of gmsh's nodes (tags, flat coordinates, mm) and tetrahedra (node tags), with
    the nodes no tetrahedron uses (the old surface's) dropped."""
    if len(tet_nodes) == 0:
        raise MeshError("gmsh produced no tetrahedra; check that the surface is closed and encloses a volume")
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    tets = index[np.asarray(tet_nodes, dtype=np.int64).reshape(-1, 4)]
    pts = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    used = np.unique(tets)
    renum = np.full(len(pts), -1, dtype=np.int64)
    renum[used] = np.arange(len(used))
    return TetMesh(pts[used], renum[tets])


def tetrahedralize_surface(
    points: np.ndarray,
    triangles: np.ndarray,
    mesh_size: float,
    *,
    interior_size: float | None = None,
    optimize: bool = True,
    feature_angle: float = 40.0,
    curvature_points: int = 0,
    timeout: float = MESH_TIMEOUT_S,
) -> TetMesh:
    """Fill a closed triangulated surface with tetrahedra using gmsh.

    The surface is re-meshed with target edge length ``mesh_size`` (smooth patches are
    re-parametrised; edges sharper than ``feature_angle`` are kept), then the volume is meshed.

    Args:
        points: (n, 3) float, mm.
        triangles: (k, 3) int, 0-based, a closed manifold surface.
        mesh_size: target edge length in mm (> 0) on the surface (and inside, by default).
        interior_size: target edge length in mm inside the volume, if different.
        optimize: run gmsh's and Netgen's quality optimisers (recommended).
        feature_angle: edges whose faces meet at a sharper angle (degrees) are kept as
            sharp edges; 180 keeps none (smooth organic surfaces).
        curvature_points: > 0 shrinks the edge length where the surface is curved, to at
            most 2 pi R / curvature_points (R the local radius of curvature); 0 = off.
        timeout: seconds after which meshing is stopped with a :class:`MeshError` (gmsh runs
            in a child process; in-process, without a limit, when the caller has already
            initialised gmsh: then its BLAS runs on the threads it was loaded with).

    Returns:
        The tetrahedral mesh (coordinates in mm).

    Raises:
        MeshError: the surface is not closed and manifold, or gmsh fails to mesh it or
            takes longer than ``timeout``.
        DependencyError: gmsh is not installed (extra ``mesh``).
    """
    _check_options(mesh_size, timeout)
    points, triangles = merge_duplicate_points(points, triangles)
    check_closed_surface(points, triangles)
    triangles = orient_surface(points, triangles)
    gmsh = require("gmsh", "mesh", "Tetrahedralising a surface")
    options = dict(mesh_size=float(mesh_size), interior_size=interior_size, optimize=optimize,
                   feature_angle=feature_angle, curvature_points=curvature_points)
    log.info("meshing a %d-triangle surface with gmsh at %.3g mm (stopped after %.0f s)", len(triangles), mesh_size,
             timeout)
    if gmsh.isInitialized():
        tags, coords, tet_nodes = run_gmsh(gmsh, points, triangles, **options)  # the caller runs gmsh
    else:
        tags, coords, tet_nodes = _gmsh_in_child(points, triangles, options, timeout)
    mesh = _tet_mesh(tags, coords, tet_nodes)
    log.info("gmsh: %d vertices, %d tetrahedra at mesh size %.3g mm", mesh.n_vertices, mesh.n_tets, mesh_size)
    return mesh
