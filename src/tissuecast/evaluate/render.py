"""3D renders (pyvista, off-screen) and VTU files of benchmark and predicted shapes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import require

__all__ = ["write_vtu", "render_comparison"]


def write_vtu(path: Path, mesh, point_data: dict) -> Path:
    """Write the tetrahedral mesh (undeformed coordinates, mm) with point data to a .vtu file.

    The same file as :func:`tissuecast.mesh.write_mesh` writes (the one mesh writer), point
    data as float64.

    Args:
        path: output file.
        mesh: the :class:`~tissuecast.mesh.TetMesh`.
        point_data: name -> (n,) or (n, 3) arrays (displacements in mm, errors in mm).
    """
    from ..mesh.io import write_mesh

    data = {k: np.asarray(v, dtype=np.float64) for k, v in point_data.items()}
    return write_mesh(path, mesh, point_data=data)[0]


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    pv = require("pyvista", "viz", "3D renders")
    pv.OFF_SCREEN = True
    return pv


def _surface(pv, mesh, u: np.ndarray | None):
    pts = np.asarray(mesh.points, dtype=np.float64) + (0.0 if u is None else u)
    tri = np.asarray(mesh.surface_triangles, dtype=np.int64)
    faces = np.hstack([np.full((len(tri), 1), 3), tri]).ravel()
    return pv.PolyData(pts, faces)


def render_comparison(path: Path, mesh, benchmark: np.ndarray, predicted: np.ndarray, title: str,
                      markers: np.ndarray | None = None, window=(1500, 500)) -> Path:
    """Three panels: undeformed, benchmark (FEM) and predicted shape coloured by vertex error.

    Args:
        path: PNG file.
        mesh: the undeformed :class:`TetMesh`.
        benchmark: (n, 3) FEM displacement, mm.
        predicted: (n, 3) predicted displacement, mm.
        title: caption of the figure.
        markers: (n_d,) marker ids drawn as spheres.
    """
    pv = _pyvista()
    err = np.linalg.norm(predicted - benchmark, axis=1)
    mag = np.linalg.norm(benchmark, axis=1)
    clim = (0.0, max(float(err.max()), 1e-6))
    p = pv.Plotter(off_screen=True, shape=(1, 3), window_size=window)
    panels = (
        ("undeformed", None, None, None),
        (f"benchmark (FEM), largest displacement {mag.max():.1f} mm", benchmark, mag, "displacement (mm)"),
        (f"predicted, vertex error (max {err.max():.2f} mm)", predicted, err, "error (mm)"),
    )
    for k, (label, u, scal, bar) in enumerate(panels):
        p.subplot(0, k)
        surf = _surface(pv, mesh, u)
        if scal is None:
            p.add_mesh(surf, color="lightgrey", show_edges=True, edge_color="grey", line_width=0.3)
        else:
            surf.point_data[bar] = scal
            p.add_mesh(surf, scalars=bar, cmap="viridis" if k == 1 else "inferno", clim=None if k == 1 else clim,
                       scalar_bar_args={"title": bar, "vertical": False, "title_font_size": 14, "label_font_size": 12,
                                        "n_labels": 2, "fmt": "%.3g", "height": 0.12, "width": 0.6,
                                        "position_x": 0.2, "position_y": 0.03})
            p.add_mesh(_surface(pv, mesh, None), style="wireframe", color="grey", opacity=0.15)
        if markers is not None and len(markers):
            pts = np.asarray(mesh.points)[markers] + (0.0 if u is None else u[markers])
            p.add_points(pts, color="red", point_size=10, render_points_as_spheres=True)
        p.add_text(label if k else f"{title}: {label}", font_size=11)
    p.link_views()
    p.view_isometric()
    p.screenshot(str(path))
    p.close()
    return path
