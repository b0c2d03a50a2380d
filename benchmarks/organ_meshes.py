"""The organ-shaped meshes of ``benchmarks/organ_speed.py``, built at run time from data that
ships with installed packages (nilearn's MNI and fsaverage templates, slicerio's chest CT), so
that nothing third-party is committed. Their sources and licences: ``organ_speed.py``'s notes.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

MESHES = ("brain", "brain-fsaverage", "phantom", "tumour", "vessel")


def _nilearn():
    """nilearn, or one line saying how to install it (not a dependency of tissuecast: only these
    benchmarks' brain meshes read its templates)."""
    try:
        import nilearn.datasets
        import nilearn.surface
    except ImportError:
        raise SystemExit("the brain meshes are built from nilearn's MNI and fsaverage templates: "
                         "pip install nilearn (or leave brain and brain-fsaverage out of --meshes)") from None
    return nilearn


def brain_label_map(path: Path) -> Path:
    """The left hemisphere of the MNI ICBM152 2009 brain mask (1 mm) as a NIfTI label map.

    The template is in RAS (the affine's x axis points to +x with the voxel index i), so the
    left hemisphere is x < 0."""
    import nibabel as nib
    load_mni152_brain_mask = _nilearn().datasets.load_mni152_brain_mask

    image = load_mni152_brain_mask(resolution=1)
    mask = np.asarray(image.get_fdata()) > 0.5
    affine = image.affine
    if not (affine[0, 0] > 0 and np.allclose(affine[:3, :3], np.diag(np.diag(affine[:3, :3])))):
        raise SystemExit("unexpected MNI template orientation: expected a diagonal RAS affine")
    x = affine[0, 0] * np.arange(mask.shape[0]) + affine[0, 3]
    left = mask & (x < 0.0)[:, None, None]
    nib.save(nib.Nifti1Image(left.astype(np.uint8), affine), str(path))
    return path


def brain_mesh(folder: Path, size: float):
    """Mesh the left-hemisphere label map by ``tissuecast mesh from-image``'s code path."""
    from tissuecast.mesh import write_mesh
    from tissuecast.mesh.from_image import mesh_from_image

    label = brain_label_map(folder / "mni152_left_hemisphere.nii.gz")
    mesh = mesh_from_image(label, size, keep_largest=True, fill_cavities=True)
    write_mesh(folder / "brain.vtu", mesh)
    return folder / "brain.vtu", mesh


def fsaverage_mesh(folder: Path, size: float):
    """FreeSurfer's fsaverage5 inflated left hemisphere (the issue's 83 x 216 x 146 mm shape),
    tetrahedralised by ``tissuecast mesh convert``'s code path."""
    import meshio

    from tissuecast.mesh import read_mesh, write_mesh

    nilearn = _nilearn()
    surface, fetch_surf_fsaverage = nilearn.surface, nilearn.datasets.fetch_surf_fsaverage

    surf = surface.load_surf_mesh(fetch_surf_fsaverage("fsaverage5")["infl_left"])
    stl = folder / "fsaverage5_inflated_left.stl"
    meshio.write(stl, meshio.Mesh(np.asarray(surf.coordinates, dtype=np.float64), [("triangle", np.asarray(surf.faces))]))
    mesh = read_mesh(stl, mesh_size=size)
    write_mesh(folder / "brain-fsaverage.vtu", mesh)
    return folder / "brain-fsaverage.vtu", mesh


def tumour_mesh(folder: Path):
    """The walkthrough's tumour label (examples/chest_tumour_label.py) meshed at 5 mm."""
    from tissuecast.mesh import write_mesh
    from tissuecast.mesh.from_image import mesh_from_image

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    import chest_tumour_label

    chest_tumour_label.main(str(folder))
    mesh = mesh_from_image(folder / "tumour.seg.nrrd", 5.0, segment="tumour")
    write_mesh(folder / "tumour.vtu", mesh)
    return folder / "tumour.vtu", mesh


def vessel_mesh(folder: Path):
    """The bent thin-walled tube (2-element wall) with its two end faces' vertices marked by the
    point-data array ``ends`` (1 there, 0 elsewhere), as ``configs/vessel.toml`` expects."""
    import meshio

    from anatomies import end_vertices
    from tissuecast.mesh.shapes import bent_tube

    mesh = bent_tube(wall_layers=2)
    ends = np.zeros(mesh.n_vertices, dtype=np.int32)
    ends[end_vertices("tube2", mesh)] = 1
    meshio.write(folder / "vessel.vtu", meshio.Mesh(mesh.points, [("tetra", mesh.tets)], point_data={"ends": ends}))
    return folder / "vessel.vtu", mesh


def add_size_arguments(ap) -> None:
    """The organ meshes' size options (``--brain-size``, ``--fsaverage-size``, mm) that
    :func:`build` reads, on the argparse parser ``ap``."""
    ap.add_argument("--brain-size", type=float, default=7.5, help="brain: gmsh size, mm (7.5: ~3400 vertices)")
    ap.add_argument("--fsaverage-size", type=float, default=7.4, help="brain-fsaverage: mesh size, mm")


def build(names: list, folder: Path, args) -> dict:
    """``{name: (mesh file or None for the built-in phantom, description)}``, each mesh built once
    into ``folder`` (a mesh file already there is reused)."""
    from tissuecast.mesh import read_mesh

    folder.mkdir(parents=True, exist_ok=True)
    makers = {"brain": lambda: brain_mesh(folder, args.brain_size),
              "brain-fsaverage": lambda: fsaverage_mesh(folder, args.fsaverage_size),
              "tumour": lambda: tumour_mesh(folder), "vessel": lambda: vessel_mesh(folder)}
    out = {}
    for name in names:
        if name not in MESHES:
            raise SystemExit(f"unknown mesh {name!r}: use {', '.join(MESHES)}")
        if name == "phantom":
            out[name] = (None, "the built-in phantom")
            continue
        path, t = folder / f"{name}.vtu", time.monotonic()
        if path.exists():
            mesh = read_mesh(path)
        else:
            path, mesh = makers[name]()
        extent = " x ".join(f"{e:.0f}" for e in mesh.extent)
        out[name] = (path, f"{mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra, {extent} mm, "
                           f"made in {time.monotonic() - t:.0f} s")
        print(f"{name}: {out[name][1]} -> {path}", flush=True)
    return out


def embedded_overrides(mesh_path, cfg) -> dict:
    """``[scenario]`` overrides that fit the embedded preset to a mesh: the access point moved to
    the most lateral-superior surface vertex (largest x + z/2, LPS) unless the preset's selects
    one, and the patch radius raised to 1.5 mean edge lengths where it is smaller."""
    from tissuecast.mesh import read_mesh

    mesh = read_mesh(mesh_path)
    surface = np.unique(mesh.surface_triangles)
    p = mesh.points
    access = cfg.scenario.indentation.access
    near = np.linalg.norm(p[surface] - np.asarray(access.point), axis=1).min()
    ind: dict = {}
    if access.rule == "distance" and near > access.distance:
        top = surface[np.argmax(p[surface, 0] + 0.5 * p[surface, 2])]
        ind["access"] = {"point": [round(float(c), 2) for c in p[top]]}
    edges = mesh.edges
    mean_edge = float(np.linalg.norm(p[edges[:, 0]] - p[edges[:, 1]], axis=1).mean())
    if cfg.scenario.indentation.radius < 1.5 * mean_edge:
        ind["radius"] = round(1.5 * mean_edge, 1)
    return {"indentation": ind} if ind else {}
