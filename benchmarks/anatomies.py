"""Every anatomy finishes: data sets on a thin-walled bent tube and a long slender body.

For each shape of :mod:`tissuecast.mesh.shapes` (structured, so the same mesh on every
machine), runs ``tissuecast.dataset.simulate`` with the paper's set-up (P2, E = 21 kPa,
nu = 0.45, 3 compact interior pins, LBO dead loads, alpha calibrated to q90 = 30 mm, the
reduced-order predictor) on a small data set, and prints: done / failed samples and the
failure reasons, the calibration (rounds, alpha, whether it converged), the phases' wall
times, the median and largest worker seconds per sample and their ratio (the time budget
stops attempts at ``dataset.time_budget`` x the running median), and the slow samples.

Shapes (``--shapes``; ``NAME@spread`` pins by the spread rule instead of the compact default;
``NAME@embedded`` holds the shape as the body would, without pins: both end faces attached and
the default elastic support, 0.0021 N/mm^3, on the whole outer surface; ``--target`` sets the
calibrated q90 peak displacement, mm):
  tube2   bent tube, radius 4 mm, wall 0.8 mm in 2 layers of tetrahedra (interior vertices only
          in the wall's middle), 90-degree bend over 60 mm, some sliver elements
  tube1   the same with a 1-element wall: no interior vertex, so no pins can be chosen; the run
          stops at once with the error that names the supports to use instead
  rod     120 x 8 x 8 mm bar bowed by 10 mm, 2 cells across (one line of interior vertices)

With compact pins the tube and the bar are held at one spot and swing and bend about it like
a hinge: the supports check refuses them at once (``tissuecast.dataset.mechanism_check``), naming the
options; with spread pins they are held against rotation (whether the data sets then
complete, and how slow their worst sample is, is what this benchmark shows).

Usage::

    python benchmarks/anatomies.py [--shapes tube1,tube2,rod,tube2@spread,rod@spread,tube1@embedded] [--samples 60]
        [--workers 2] [--target 30]

Wall-clock figures on a machine shared with other jobs are inflated; the ratio of the
slowest sample to the median is the figure to read.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

def make_shape(name: str):
    """The mesh of a shape named in the module notes."""
    from tissuecast.mesh.shapes import bent_tube, slender_rod

    if name.startswith("tube"):
        return bent_tube(wall_layers=int(name[4:]))
    if name == "rod":
        return slender_rod(cells_across=2)
    raise SystemExit(f"unknown shape {name!r}: use tube1, tube2 or rod")


def end_vertices(name: str, mesh) -> np.ndarray:
    """0-based ids of the vertices on the two end faces of a tube or rod (its first and last
    cross-sections: the shapes number their vertices section by section along the centre line)."""
    per_section = {"tube1": 24 * 2, "tube2": 24 * 3, "rod": 3 * 3}[name]
    n = mesh.n_vertices
    if n % per_section:
        raise SystemExit(f"{name}: {n} vertices is not a whole number of {per_section}-vertex sections")
    return np.r_[np.arange(per_section), np.arange(n - per_section, n)]


def run_shape(name: str, args) -> None:
    from tissuecast.config import Config, with_overrides
    from tissuecast.dataset import SampleStatus, open_dataset, simulate
    from tissuecast.errors import TissuecastError
    from tissuecast.mesh import write_mesh

    name, _, rule = name.partition("@")
    folder = Path(tempfile.mkdtemp(prefix=f"tc-{name}-"))
    mesh = make_shape(name)
    write_mesh(folder / "mesh.vtu", mesh)
    q = mesh.quality
    held = f"{rule or 'compact'}{'' if rule == 'embedded' else ' pins'}"
    print(f"\n{name}, {held}: {mesh.n_vertices} vertices ({len(mesh.interior_vertices)} interior), "
          f"{mesh.n_tets} tetrahedra, "
          f"radius ratio min {q.radius_ratio_min:.3f} mean {q.radius_ratio_mean:.3f}, extent "
          f"{np.round(mesh.extent, 1).tolist()} mm", flush=True)
    n2 = max(args.samples // 10, 1)
    over = {}
    if rule == "embedded":  # held as in the body: both open ends attached, springs on the whole surface
        ends = end_vertices(name, mesh)
        over = {"scenario": {"name": "embedded", "pins": False, "attached": {"rule": "ids", "ids": ends.tolist()},
                             "springs": {"rule": "surface"}}}
        print(f"  embedded: {len(ends)} vertices of the two ends attached, springs "
              f"{Config().scenario.springs.normal_stiffness:g} N/mm^3 on the outer surface", flush=True)
    cfg = with_overrides(Config(), mesh={"path": str(folder / "mesh.vtu")},
                         markers={"fixed_rule": "compact" if rule in ("", "embedded") else rule},
                         forces={"target_max_displacement": args.target},
                         dataset={"n_samples": args.samples, "n_test2": n2, "workers": args.workers,
                                  "calibration_samples": args.pilots, "predictor_samples": args.basis}, **over)
    t = time.perf_counter()
    try:
        s = simulate(cfg, folder / "set.zarr", progress=True)
    except TissuecastError as exc:
        print(f"  stopped after {time.perf_counter() - t:.1f} s with {type(exc).__name__}: {exc}", flush=True)
        return
    ds = open_dataset(folder / "set.zarr")
    run, cal = s["run"], s["calibration"]
    done = ds.status == SampleStatus.DONE
    sec = ds.seconds[ds.status > 0]
    med = float(np.median(sec))
    print(f"  {int(done.sum())} done, {s['totals']['failed']} failed of {len(ds)} in {time.perf_counter() - t:.0f} s; "
          f"calibration {len(cal['rounds'])} rounds, alpha {cal['alpha']:.4g} N, q90 {cal['quantile_value']:.1f} mm, "
          f"converged {cal['converged']}; phases: calibration {run['calibration_seconds']:.0f} s, reduced model "
          f"{run.get('reduced_seconds', 0.0):.0f} s, samples {run['sample_phase_seconds']:.0f} s")
    print(f"  worker seconds per sample: median {med:.2f}, max {sec.max():.2f} ({sec.max() / med:.1f}x the median); "
          f"slow samples {len(run['slow_samples'])}, stopped by the budget {len(run['stopped_by_budget'])}")
    md = s["max_displacement"]
    if md:
        print(f"  peak displacement per sample: median {md['median']:.1f}, p90 {md['p90']:.1f}, max {md['max']:.1f} mm")
    for i, reason in list(ds.failures.items())[:5]:
        print(f"  failed sample {i}: {reason[:400]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shapes", default="tube1,tube2,rod,tube2@spread,rod@spread")
    ap.add_argument("--samples", type=int, default=60, help="LBO samples (test-2: a tenth of it)")
    ap.add_argument("--pilots", type=int, default=12, help="calibration pilots")
    ap.add_argument("--basis", type=int, default=20, help="reduced-model basis samples")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--target", type=float, default=30.0, help="q90 of the peak displacement the forces are calibrated to, mm")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("tissuecast.fem").setLevel(logging.WARNING)
    for name in args.shapes.split(","):
        run_shape(name, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
