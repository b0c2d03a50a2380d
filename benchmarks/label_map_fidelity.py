"""Label map -> tetrahedral mesh: volume and Hausdorff figures against the voxels, per shape.

Targets (issue 18): volume within 2 % of the labelled voxel volume, surface within one voxel
(Hausdorff) of the label boundary. Rows: closed-form ellipsoids on oblique, anisotropic grids
(the test shapes), the walkthrough's tumour label on slicerio's chest CT grid, and with
``--real`` the right lung of slicerio's real chest CT segmentation (slow, ~20-40 s).

Usage: python benchmarks/label_map_fidelity.py [--real]
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "examples"))

from labelmap_factories import ELLIPSOIDS, ellipsoid_mask  # noqa: E402

from tissuecast.mesh.from_image import label_map_fidelity, label_pieces, mesh_label_map  # noqa: E402
from tissuecast.mesh.labelmap import LabelMap, read_label_map  # noqa: E402


def rows(real: bool):
    for name, (semi, spacing, size) in ELLIPSOIDS.items():
        mask, ijk_to_lps, _ = ellipsoid_mask(semi, spacing)
        exact = 4.0 / 3.0 * np.pi * np.prod(semi)
        yield name, LabelMap(mask, ijk_to_lps, "ellipsoid"), size, exact
    import tempfile

    import chest_tumour_label

    with tempfile.TemporaryDirectory() as tmp:
        chest_tumour_label.main(tmp)
        tumour = read_label_map(os.path.join(tmp, "tumour.seg.nrrd"), segment="tumour")
    yield "walkthrough tumour on the chest CT grid", tumour, 5.0, None
    if real:
        import slicerio

        path = os.path.join(os.path.dirname(slicerio.__file__), "data", "Segmentation.seg.nrrd")
        lung = read_label_map(path, segment="right lung")
        piece = LabelMap(label_pieces(lung.mask, keep_largest=True, fill_cavities=True), lung.ijk_to_lps, "right lung")
        yield "right lung, slicerio chest CT (real)", piece, 10.0, None


def main(argv: list[str]) -> int:
    print(f"{'label':44s} {'size':>5s} {'verts':>6s} {'vol err':>8s} {'H vox':>6s} {'H mm':>6s} {'rr min':>6s} {'vs exact':>8s} {'time':>6s}")
    for name, labelmap, size, exact in rows("--real" in argv):
        start = time.perf_counter()
        mesh = mesh_label_map(labelmap, size)
        f = label_map_fidelity(mesh, labelmap)
        sec = time.perf_counter() - start
        vs = f"{100 * (mesh.volume - exact) / exact:+7.2f}%" if exact else "       -"
        print(f"{name:44s} {size:5.1f} {mesh.n_points:6d} {100 * f.volume_error:+7.2f}% {f.hausdorff_voxels:6.2f} "
              f"{f.hausdorff_mm:6.2f} {mesh.quality.radius_ratio_min:6.3f} {vs} {sec:5.1f}s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
