"""A real brain label map meshed within a vertex budget: vertices, tetrahedra, fidelity, cost.

The label map is built from the MNI ICBM152 2009a nonlinear symmetric grey- and white-matter
probability maps (1 mm, 197 x 233 x 189 voxels) that ship inside the nilearn wheel
(``nilearn/datasets/data/mni_icbm152_{gm,wm}_tal_nlin_sym_09a_converted.nii.gz``, read
offline; ``pip install nilearn`` is needed for this benchmark only, it is no dependency of
tissuecast). Template: V. Fonov, A. Evans, R. McKinstry, C. Almli, D. L. Collins, "Unbiased
nonlinear average age-appropriate brain templates from birth to adulthood", NeuroImage 2009,
and Fonov et al., NeuroImage 2011. Licence: nilearn's description states it as "unknown"; the
McConnell Brain Imaging Centre distributes the ICBM 2009 templates under a copyright notice
of D. L. Collins (Montreal Neurological Institute, McGill University) that permits use,
copying and distribution with the notice kept. Nothing of it is copied into this repository:
the label map is written to a temporary folder (or ``--keep FOLDER``) and never committed.

Label: voxels whose grey- plus white-matter probability is at least 0.5 (brain tissue); the
largest face-connected piece, internal cavities (ventricles) filled. ``--region`` picks:

- ``brain``: the whole label (about 1750 cm^3; the template's average is blurrier than one
  brain, so larger);
- ``posterior``: the label behind y = -35 mm and below z = -15 mm (MNI): the cerebellum,
  brainstem and the occipital poles above them, about 210 cm^3 (the size of the label map of
  issue 32), with flat cut faces;
- ``right``: the right hemisphere (x > 2 mm, MNI), about 850 cm^3.

It then runs ``tissuecast mesh from-image LABEL OUT.vtu --max-vertices N --keep-largest
--fill-cavities --json`` in-process and prints the vertices, tetrahedra, volume error, the
95th-percentile distances both ways (mesh surface to the label's voxel boundary, and the
boundary to the mesh: large where the mesh bridges sulci narrower than its elements) and the
HD95 (their larger) in voxels and mm, and the expected paper-size run time printed by the
command. Timings are wall-clock on whatever machine runs it.

    python benchmarks/brain_label_map.py --region brain --max-vertices 5000
    python benchmarks/brain_label_map.py --region posterior --max-vertices 5000
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
import time
from pathlib import Path

import numpy as np

TEMPLATE = "mni_icbm152_{}_tal_nlin_sym_09a_converted.nii.gz"
REGIONS = ("brain", "posterior", "right")


def template_path(kind: str) -> Path:
    """The nilearn-bundled probability map ``kind`` ('gm' or 'wm')."""
    import nilearn.datasets

    path = Path(nilearn.datasets.__file__).parent / "data" / TEMPLATE.format(kind)
    if not path.is_file():
        raise SystemExit(f"{path} is missing: this nilearn wheel does not bundle the MNI152 templates")
    return path


def brain_label_map(region: str, folder: Path, resolution: int = 1) -> Path:
    """Write the label map (NIfTI, the template's RAS affine; label 1) and return its path."""
    import nibabel as nib

    gm, wm = (nib.load(template_path(k)) for k in ("gm", "wm"))
    tissue = (np.asarray(gm.dataobj, dtype=np.float32) + np.asarray(wm.dataobj, dtype=np.float32)) / 255.0
    affine = gm.affine.copy()
    if resolution > 1:  # block means of the probabilities
        r = resolution
        shape = np.array(tissue.shape) // r
        tissue = tissue[: shape[0] * r, : shape[1] * r, : shape[2] * r].reshape(shape[0], r, shape[1], r, shape[2], r)
        tissue = tissue.mean(axis=(1, 3, 5))
        affine[:3, :3] *= r
        affine[:3, 3] += affine[:3, :3] @ np.full(3, (1.0 - r) / (2.0 * r))
    label = tissue >= 0.5
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in label.shape], indexing="ij"), axis=-1)
    mni = ijk @ affine[:3, :3].T + affine[:3, 3]  # RAS mm
    if region == "posterior":
        label &= (mni[..., 1] < -35.0) & (mni[..., 2] < -15.0)
    elif region == "right":
        label &= mni[..., 0] > 2.0
    path = folder / f"{region}_{resolution}mm.nii.gz"
    nib.save(nib.Nifti1Image(label.astype(np.uint8), affine), str(path))
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--region", choices=REGIONS, default="brain")
    parser.add_argument("--max-vertices", type=int, default=5000)
    parser.add_argument("--resolution", type=int, choices=(1, 2), default=1, help="voxel size of the label map, mm")
    parser.add_argument("--keep", metavar="FOLDER", help="keep the label map and the mesh in FOLDER (never commit them)")
    args = parser.parse_args(argv)
    from tissuecast.cli.main import main as tissuecast

    with contextlib.ExitStack() as stack:
        folder = Path(args.keep) if args.keep else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        folder.mkdir(parents=True, exist_ok=True)
        scan = brain_label_map(args.region, folder, args.resolution)
        out = io.StringIO()
        started = time.perf_counter()
        with contextlib.redirect_stdout(out):
            status = tissuecast(["-q", "mesh", "from-image", str(scan), str(folder / f"{scan.name[:-7]}.vtu"),
                                 "--max-vertices", str(args.max_vertices), "--keep-largest", "--fill-cavities",
                                 "--json"])
        seconds = time.perf_counter() - started
        if status:
            return status
        report(json.loads(out.getvalue()), args, seconds)
    return 0


def report(doc: dict, args, seconds: float) -> None:
    """Print the figures of one run next to the targets."""
    from tissuecast.mesh.run_cost import duration_text

    f, sizing, cost = doc["fidelity"], doc["sizing"], doc["paper_run"]
    voxel = float(np.mean(doc["spacing_mm"]))
    print(f"label map          {args.region}, {args.resolution} mm voxels, {f['label_volume'] / 1000:.1f} cm^3 "
          "(MNI ICBM152 2009a grey + white matter >= 0.5, nilearn)")
    print(f"budget             {args.max_vertices} vertices: {doc['vertices']} vertices, {doc['tetrahedra']} tetrahedra "
          f"(target <= {args.max_vertices}: {'met' if doc['vertices'] <= args.max_vertices else 'NOT met'}), "
          f"edge length {sizing['size_mm']:.2f} mm, {len(sizing['attempts'])} meshing attempt(s)")
    print(f"volume error       {100 * f['volume_error']:+.2f} %")
    print(f"surface p95        mesh surface to the label boundary {f['surface_p95_voxels']:.2f} voxels = "
          f"{f['surface_p95_mm']:.2f} mm (target <= 2 voxels: {'met' if f['surface_p95_voxels'] <= 2 else 'NOT met'})")
    print(f"boundary p95       label boundary to the mesh {f['boundary_p95_voxels']:.2f} voxels = "
          f"{f['boundary_p95_mm']:.2f} mm")
    print(f"HD95               {f['hausdorff95_voxels']:.2f} voxels = {f['hausdorff95_mm']:.2f} mm "
          f"(Hausdorff {f['hausdorff_mm']:.2f} mm; voxel {voxel:.2g} mm)")
    print(f"quality            radius ratio min {doc['quality']['radius_ratio_min']:.3f}, "
          f"mean {doc['quality']['radius_ratio_mean']:.3f}")
    print(f"expected run       {duration_text(cost['seconds'])} for a paper-size run ({cost['unknowns']:,} unknowns, "
          f"t ~ n^{cost['exponent']:.2f}{', extrapolated' if cost['extrapolated'] else ''})")
    print(f"meshing            {seconds:.0f} s wall-clock (search, fidelity, files)")


if __name__ == "__main__":
    raise SystemExit(main())
