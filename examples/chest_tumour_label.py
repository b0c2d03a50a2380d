"""Write the walkthrough's label map: a tumour-shaped label in the right lung of a real chest CT.

The CT (``CTChest4.nrrd``, 128 x 128 x 34 voxels of 3.05 x 3.05 x 10 mm, LPS, axes (-1, -1, 1))
ships with the ``slicerio`` package (installed by tissuecast's ``image`` extra), so nothing is
downloaded. The label is an ellipsoid (semi-axes 30 x 22 x 35 mm, tilted 20 degrees) drawn on
the CT's own voxel grid and saved as a 3D Slicer segmentation with one segment, ``tumour``:
load it in Slicer on top of the CT and the two line up.

Usage: python examples/chest_tumour_label.py OUT_DIR
Writes OUT_DIR/tumour.seg.nrrd and prints the CT's path.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import slicerio
from scipy.spatial.transform import Rotation

CENTRE_LPS = np.array([-75.0, 15.0, -145.0])  # mm, in the right lung
SEMI_AXES = np.array([30.0, 22.0, 35.0])  # mm
TILT = Rotation.from_euler("y", 20.0, degrees=True).as_matrix()


def ct_path() -> str:
    return os.path.join(os.path.dirname(slicerio.__file__), "data", "CTChest4.nrrd")


def main(out_dir: str) -> int:
    ct = slicerio.read_volume(ct_path())
    shape = list(ct["voxels"].shape)
    ijk_to_lps = np.asarray(ct["ijkToLPS"])
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    local = (ijk @ ijk_to_lps[:3, :3].T + ijk_to_lps[:3, 3] - CENTRE_LPS) @ TILT
    mask = (((local / SEMI_AXES) ** 2).sum(axis=1) <= 1.0).reshape(shape)
    segmentation = slicerio.create_segmentation(shape, ijk_to_lps)
    slicerio.add_segment(segmentation, mask, {"name": "tumour", "color": [0.9, 0.6, 0.2]})
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    slicerio.write_segmentation(str(out / "tumour.seg.nrrd"), segmentation)
    print(f"wrote {out / 'tumour.seg.nrrd'}: segment 'tumour', {int(mask.sum())} voxels on the CT grid")
    print(f"CT: {ct_path()}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "walkthrough"))
