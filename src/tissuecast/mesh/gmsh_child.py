"""The meshing child process: ``python -m tissuecast.mesh.gmsh_child JOB OUT``.

:func:`tissuecast.mesh.mesher.tetrahedralize_surface` runs gmsh here, in a fresh Python
process started with :data:`~tissuecast.mesh.mesher.GMSH_ENVIRONMENT`, so that gmsh's own
BLAS starts on one thread and a hang can be killed. ``JOB`` is an ``.npz`` file with
``points`` (n, 3) float64 mm, ``triangles`` (k, 3) int64 (0-based) and ``options`` (a JSON
object of :func:`~tissuecast.mesh.mesher.run_gmsh`'s keywords); the answer goes to ``OUT``
(``.npz``: gmsh's node ``tags``, flat ``coords`` mm and ``tet_nodes``), or gmsh's error
message to ``OUT`` with the suffix :data:`~tissuecast.mesh.mesher.CHILD_ERROR_SUFFIX` (exit status 1). Neither file is pickled.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> int:
    """Mesh the job ``argv[0]`` into ``argv[1]``; 0 on success, 1 with the error written."""
    from ..errors import MeshError
    from .mesher import CHILD_ERROR_SUFFIX, run_gmsh

    job, out = Path(argv[0]), Path(argv[1])
    with np.load(job, allow_pickle=False) as z:
        points, triangles, options = z["points"], z["triangles"], json.loads(str(z["options"]))
    import gmsh

    try:
        tags, coords, tet_nodes = run_gmsh(gmsh, points, triangles, **options)
    except MeshError as exc:
        out.with_suffix(CHILD_ERROR_SUFFIX).write_text(str(exc))
        return 1
    np.savez(out, tags=tags, coords=coords, tet_nodes=tet_nodes)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
