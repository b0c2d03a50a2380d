"""Test anatomies: the phantom at other resolutions, a dome, a slender body and a thin-walled tube.

These shapes exercise the solver and the data-set generator where the built-in phantom does
not: patient-size meshes (many more degrees of freedom), long slender bodies, and
thin-walled vessels whose wall is one or two tetrahedra thick (almost no interior vertices,
some flat elements). ``benchmarks/scaling.py`` and the tests use them.

* :func:`phantom_mesh` and :func:`dome_mesh` mesh a smooth closed surface with gmsh (extra
  ``mesh``). gmsh's output depends on its version and may depend on the CPU (not on the
  machine's core count: :mod:`.mesher`), so callers check their counts with tolerances.
* :func:`bent_tube` and :func:`slender_rod` are structured (no gmsh): the same arrays on every
  machine.

Coordinates in mm.
"""

from __future__ import annotations

import numpy as np

from .phantom import PHANTOM_INTERIOR_SIZE, PHANTOM_MESH_SIZE, icosphere, phantom_surface
from .tetmesh import TetMesh

__all__ = ["phantom_mesh", "dome_surface", "dome_mesh", "bent_tube", "slender_rod", "DOME_EXTENT"]

#: (3,) mm: bounding box of :func:`dome_surface`, about a brain hemisphere's half (x, y, z).
DOME_EXTENT = (60.0, 90.0, 55.0)

# The six tetrahedra of a hexahedral cell split along its diagonal from local corner 0 to 7
# (corner id = i + 2 j + 4 k for the offsets (i, j, k)); neighbouring cells split their
# shared faces the same way, so the mesh is conforming.
_KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def phantom_mesh(scale: float = 1.0) -> TetMesh:
    """The phantom's surface meshed by gmsh with its element sizes times ``scale``.

    ``scale = 1`` gives about the shipped phantom (~1170 vertices); the vertex count grows
    roughly like ``scale^-3`` (0.55: ~5900 vertices, 0.45: ~10 000).

    Args:
        scale: factor (> 0) on ``PHANTOM_MESH_SIZE`` and ``PHANTOM_INTERIOR_SIZE``.
    """
    from .mesher import tetrahedralize_surface

    points, triangles = phantom_surface()
    return tetrahedralize_surface(points, triangles, PHANTOM_MESH_SIZE * scale,
                                  interior_size=PHANTOM_INTERIOR_SIZE * scale)


def dome_surface(subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A smooth dome (half an ellipsoid on a rounded, flattened base) of :data:`DOME_EXTENT`.

    Star-shaped about its centre (each direction ``d`` of the unit sphere is moved to
    ``r(d) d``), so the surface is embedded. The lower corner of the bounding box is at the
    origin.

    Returns:
        (points (n, 3) float mm, triangles (k, 3) int, outward).
    """
    d, tri = icosphere(subdivisions)
    p = d.copy()
    below = p[:, 2] < 0.0
    p[below, 2] *= 0.35  # a flattened, still smooth, base
    p[:, 2] += 0.06 * np.sin(3.0 * p[:, 0]) * np.cos(2.0 * p[:, 1])  # gentle gyri-like ripples
    p -= p.min(axis=0)
    p *= np.asarray(DOME_EXTENT) / p.max(axis=0)
    return p, tri


def dome_mesh(mesh_size: float) -> TetMesh:
    """:func:`dome_surface` filled with tetrahedra of about ``mesh_size`` mm (gmsh)."""
    from .mesher import tetrahedralize_surface

    return tetrahedralize_surface(*dome_surface(), mesh_size, feature_angle=180.0)


def _hex_grid_tets(shape: tuple[int, int, int], periodic_j: bool) -> np.ndarray:
    """Kuhn tetrahedra of a structured (ni, nj, nk) grid of cells; vertex (i, j, k) has id
    ``(i * nj' + j) * (nk + 1) + k`` with ``nj' = nj`` when j wraps around, else ``nj + 1``."""
    ni, nj, nk = shape
    njv = nj if periodic_j else nj + 1
    i, j, k = np.meshgrid(np.arange(ni), np.arange(nj), np.arange(nk), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    corners = []
    for c in range(8):
        di, dj, dk = c & 1, (c >> 1) & 1, (c >> 2) & 1
        jj = (j + dj) % njv if periodic_j else j + dj
        corners.append(((i + di) * njv + jj) * (nk + 1) + k + dk)
    corners = np.stack(corners, axis=1)
    return corners[:, _KUHN].reshape(-1, 4)


def bent_tube(
    radius: float = 4.0,
    wall: float = 0.8,
    wall_layers: int = 1,
    length: float = 60.0,
    bend_angle: float = 90.0,
    around: int = 24,
    along: int = 40,
    jitter: float = 0.2,
    seed: int = 0,
) -> TetMesh:
    """A thin-walled vessel: a tube bent along a circular arc, its wall ``wall_layers`` cells thick.

    The centre line is an arc of length ``length`` turning by ``bend_angle`` degrees in the
    x-z plane; the wall spans radii ``[radius - wall, radius]``; cells are split into six
    tetrahedra each. With one layer no vertex is interior; with two only the middle layer is.
    Vertices are moved by a deterministic random amount (``jitter`` times the local cell size,
    along the wall and through it), which leaves some flat (sliver) elements, as meshes of
    real vessels have.

    Args:
        radius: outer radius, mm.  wall: wall thickness, mm (< radius).
        wall_layers: cells through the wall (1 or 2 make the hard cases; any >= 1 allowed).
        length: length of the centre line, mm.  bend_angle: degrees (0 = straight).
        around, along: cells around the circumference and along the centre line.
        jitter: random displacement of each vertex as a share of the cell size (< 0.5).
        seed: the jitter's random seed.

    Returns:
        The tube (its open ends are part of its surface).
    """
    if not 0.0 < wall < radius or wall_layers < 1 or around < 3 or along < 1 or not 0.0 <= jitter < 0.5:
        raise ValueError("bent_tube needs 0 < wall < radius, wall_layers >= 1, around >= 3, along >= 1, "
                         f"0 <= jitter < 0.5; got wall {wall}, radius {radius}, wall_layers {wall_layers}, "
                         f"around {around}, along {along}, jitter {jitter}")
    s = np.linspace(0.0, length, along + 1)
    theta = 2.0 * np.pi * np.arange(around) / around
    r = np.linspace(radius - wall, radius, wall_layers + 1)
    rng = np.random.default_rng(seed)
    ss, tt, rr = np.meshgrid(s, theta, r, indexing="ij")
    ss = ss + jitter * (length / along) * rng.uniform(-1, 1, ss.shape) * (0 < ss) * (ss < length)
    tt = tt + jitter * (2.0 * np.pi / around) * rng.uniform(-1, 1, tt.shape)
    rr = rr + jitter * (wall / wall_layers) * rng.uniform(-1, 1, rr.shape)
    phi = np.radians(bend_angle) * ss / length  # direction of the centre line at s
    if bend_angle:
        bend_radius = length / np.radians(bend_angle)
        cx, cz = bend_radius * (1.0 - np.cos(phi)), bend_radius * np.sin(phi)
    else:
        cx, cz = np.zeros_like(ss), ss
    # frame: normal (cos phi, 0, -sin phi) in the bend plane, binormal y
    x = cx + rr * np.cos(tt) * np.cos(phi)
    y = rr * np.sin(tt)
    z = cz - rr * np.cos(tt) * np.sin(phi)
    points = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    points -= points.min(axis=0)
    return TetMesh(points, _hex_grid_tets((along, around, wall_layers), periodic_j=True))


def slender_rod(length: float = 120.0, width: float = 8.0, cells_along: int = 60, cells_across: int = 3,
                bend: float = 10.0) -> TetMesh:
    """A long thin body: a ``length`` x ``width`` x ``width`` mm bar, gently bent.

    ``cells_across`` cells across (1: no interior vertex; 2: one line of them along the
    bar; 3: four lines), the centre line bowed by ``bend`` mm at mid-length (a parabola in
    x), structured Kuhn tetrahedra.

    Args:
        length, width: mm.  cells_along, cells_across: cells per direction (>= 1).
        bend: sag of the centre line at mid-length, mm.
    """
    if cells_along < 1 or cells_across < 1 or not (length > 0 and width > 0):
        raise ValueError(f"slender_rod needs positive sizes and cell counts, got length {length}, width {width}, "
                         f"cells_along {cells_along}, cells_across {cells_across}")
    z = np.linspace(0.0, length, cells_along + 1)
    a = np.linspace(0.0, width, cells_across + 1)
    zz, yy, xx = np.meshgrid(z, a, a, indexing="ij")
    xx = xx + bend * (1.0 - (2.0 * zz / length - 1.0) ** 2)
    points = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
    return TetMesh(points, _hex_grid_tets((cells_along, cells_across, cells_across), periodic_j=False))
