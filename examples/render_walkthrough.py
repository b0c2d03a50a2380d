"""Render the walkthrough's picture: the predicted tumour surface over a slice of the CT.

Everything is drawn in LPS mm, the frame of the CT and of the mesh: the model predicts a
test-1 sample of its own data set from its 5 markers; the picture shows the CT's axial slice
through the tumour, the undeformed surface (white mesh), the predicted deformed surface
coloured by displacement, its cut with the slice (red) and the markers (black).

Usage: python examples/render_walkthrough.py [RUN_DIR] [OUT.png]
(defaults: walkthrough/run, docs/img/walkthrough_chest_tumour.png)
"""

from __future__ import annotations

import os
import sys

import numpy as np


def main(run_dir: str = "walkthrough/run", out: str = "docs/img/walkthrough_chest_tumour.png") -> int:
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv
    import slicerio

    from tissuecast.dataset import open_dataset
    from tissuecast.surrogate import DeformationModel

    pv.OFF_SCREEN = True
    model = DeformationModel.load(os.path.join(run_dir, "model"))
    dataset = open_dataset(os.path.join(run_dir, "dataset.zarr"))
    sample = int(dataset.select("test1")[0])
    fem = np.asarray(dataset.displacements[sample], dtype=np.float64)
    u = model.predict(model.marker_displacements(fem))
    mesh = model.mesh

    ct = slicerio.read_volume(os.path.join(os.path.dirname(slicerio.__file__), "data", "CTChest4.nrrd"))
    voxels, ijk_to_lps = np.asarray(ct["voxels"], dtype=np.float32), np.asarray(ct["ijkToLPS"])
    centre = mesh.points.mean(axis=0)
    k = int(round(np.linalg.solve(ijk_to_lps[:3, :3], centre - ijk_to_lps[:3, 3])[2]))
    ni, nj = voxels.shape[:2]
    ii, jj = np.meshgrid(np.arange(ni), np.arange(nj), indexing="ij")
    ijk = np.stack([ii, jj, np.full_like(ii, k)], axis=-1).reshape(-1, 3).astype(float)
    xyz = ijk @ ijk_to_lps[:3, :3].T + ijk_to_lps[:3, 3]
    slice_grid = pv.StructuredGrid(*(xyz[:, a].reshape(ni, nj, 1) for a in range(3)))
    slice_grid.point_data["HU"] = voxels[:, :, k].ravel(order="F")

    tri = mesh.surface_triangles
    faces = np.c_[np.full(len(tri), 3), tri].ravel()
    before = pv.PolyData(mesh.points, faces)
    after = pv.PolyData(mesh.points + u, faces)
    after.point_data["displacement (mm)"] = np.linalg.norm(u, axis=1)
    z = ijk_to_lps[2, 3] + ijk_to_lps[2, 2] * k
    cut = after.slice(normal=(0, 0, 1), origin=(centre[0], centre[1], z))

    plotter = pv.Plotter(off_screen=True, window_size=[1400, 1000])
    plotter.set_background("white")
    plotter.add_mesh(slice_grid, scalars="HU", cmap="gray", clim=(-1000, 400), show_scalar_bar=False)
    plotter.add_mesh(before, style="wireframe", color="white", opacity=0.35, line_width=1)
    plotter.add_mesh(after, scalars="displacement (mm)", cmap="viridis", opacity=0.85,
                     scalar_bar_args={"title": "predicted displacement (mm)", "color": "black"})
    if cut.n_points:
        plotter.add_mesh(cut, color="red", line_width=4)
    radius = 0.03 * float(np.linalg.norm(mesh.extent))
    for p in (mesh.points + u)[model.markers]:
        plotter.add_mesh(pv.Sphere(radius=radius, center=p), color="black")
    plotter.add_text(f"CT slice {k} (z = {z:.0f} mm, LPS) with the predicted tumour surface", font_size=14, color="white", shadow=True)
    plotter.camera_position = [tuple(centre + np.array([120.0, 260.0, 330.0])), tuple(centre), (0.0, 0.0, 1.0)]
    plotter.camera.zoom(1.25)
    plotter.add_axes(xlabel="L", ylabel="P", zlabel="S")
    plotter.screenshot(out)
    plotter.close()
    print(f"wrote {out} (test-1 sample {sample}, peak displacement {np.linalg.norm(fem, axis=1).max():.1f} mm FEM, "
          f"max vertex error {np.linalg.norm(u - fem, axis=1).max():.2f} mm)")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
