"""Regenerate the built-in phantom mesh ``src/tissuecast/data/phantom.npz``.

The surface is tissuecast's own analytic shape (:func:`tissuecast.mesh.phantom.phantom_surface`);
gmsh (extra ``mesh``) fills it with tetrahedra. gmsh output can change between gmsh versions
and platforms, which is why the result is shipped rather than generated at run time; after
regenerating, update the expected counts and fingerprint in tests/mesh/test_mesh_phantom.py.

The shipped phantom was made with gmsh's bundled BLAS on two threads (gmsh 4.15.2: 1165
vertices, 5066 tetrahedra; the same bits again on a 2-core machine with the code of then).
Meshing now pins that BLAS to one thread (:data:`tissuecast.mesh.mesher.GMSH_ENVIRONMENT`),
which gives another mesh of the same surface (1168 vertices, 5078 tetrahedra there):
regenerating replaces the phantom, and with it every figure measured on it.

Usage: python scripts/make_phantom.py [OUT.npz]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from tissuecast.mesh.mesher import tetrahedralize_surface
from tissuecast.mesh.phantom import PHANTOM_INTERIOR_SIZE, PHANTOM_MESH_SIZE, phantom_surface


def main(argv: list[str]) -> int:
    out = Path(argv[0]) if argv else Path(__file__).resolve().parents[1] / "src" / "tissuecast" / "data" / "phantom.npz"
    gmsh = __import__("gmsh")
    points, triangles = phantom_surface()
    mesh = tetrahedralize_surface(points, triangles, PHANTOM_MESH_SIZE, interior_size=PHANTOM_INTERIOR_SIZE)
    np.savez_compressed(
        out,
        points=mesh.points,
        tets=mesh.tets.astype(np.int64),
        gmsh_version=np.array(gmsh.__version__),
        mesh_size=np.array([PHANTOM_MESH_SIZE, PHANTOM_INTERIOR_SIZE]),
    )
    q = mesh.quality
    print(f"wrote {out}")
    print(f"vertices {mesh.n_vertices}, tetrahedra {mesh.n_tets}, surface vertices {len(mesh.surface_vertices)}, "
          f"surface triangles {len(mesh.surface_triangles)}")
    print(f"extent {np.round(mesh.extent, 3).tolist()} mm, volume {mesh.volume:.3f} mm^3, "
          f"radius ratio min {q.radius_ratio_min:.3f} mean {q.radius_ratio_mean:.3f}")
    print(f"fingerprint {mesh.fingerprint()}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
