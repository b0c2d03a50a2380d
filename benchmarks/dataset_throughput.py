"""Data-set generation throughput on the paper-size phantom (P2), and where the time goes.

Runs ``tissuecast.dataset.simulate`` on the built-in phantom with the paper's set-up (P2,
E = 21 kPa, nu = 0.45, 3 fixed interior vertices, 20 LBO modes, alpha calibrated to 30 mm)
for a small data set in the paper's LBO : test-2 mix, then prints

* samples per minute (sample phase, after calibration) and the calibration's fixed cost,
* the projected time of the full paper data set (2000 LBO + 200 test-2) and its ratio to
  the 15-minute target,
* parent-process I/O per sample, and a cProfile split of one worker's solve time into
  tangent assembly, residual/energy assembly, factorisation, triangular solves and the rest.

Usage::

    python benchmarks/dataset_throughput.py [--samples 40] [--workers 2] [--profile 2] [--alpha A]

Timings on a machine shared with other jobs are inflated; say so when quoting them.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"  # the in-process profile runs like a worker: single-threaded BLAS

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402


PAPER_SAMPLES = 2000 + 200
TARGET_MINUTES = 15.0

# cProfile buckets: (label, predicate on (file, function name))
_BUCKETS = [
    ("tangent assembly", lambda f, n: f.endswith("assembly.py") and n == "tangent"),
    ("residual/energy assembly", lambda f, n: f.endswith("assembly.py") and n in ("energy_and_force", "internal_force", "energy")),
    ("factorisation", lambda f, n: f.endswith("linear.py") and n == "factorize"),
    ("triangular solves", lambda f, n: f.endswith("linear.py") and n == "solve"),
]


def _profile(cfg, alpha: float, count: int) -> tuple[dict, float, int]:
    """Solve ``count`` LBO samples in this process under cProfile; seconds per bucket."""
    from tissuecast.dataset import make_plan
    from tissuecast.dataset.generate import setup_from_config
    from tissuecast.dataset.worker import Recipe, Task, context_for, solve_task
    from tissuecast.config import config_to_toml
    from tissuecast.forces import lbo_basis

    mesh, _, fixed = setup_from_config(cfg)
    basis = lbo_basis(mesh, cfg.forces.n_basis)
    recipe = Recipe(config_to_toml(cfg, comments=False), mesh.points, mesh.tets, fixed,
                    basis.vertices, basis.vectors, basis.eigenvalues, basis.mass)
    t = time.perf_counter()
    context_for(recipe).solver(0)
    setup = time.perf_counter() - t
    plan = make_plan(cfg)
    prof = cProfile.Profile()
    prof.enable()
    results = [solve_task(recipe, Task(i, int(plan.seed[i]), float("nan"), alpha)) for i in range(count)]
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = sum(r.seconds for r in results)
    out = {}
    for label, pred in _BUCKETS:
        out[label] = sum(v[3] for (f, _, n), v in stats.items() if pred(f, n))  # cumulative time
    out["other"] = max(total - sum(out.values()), 0.0)
    return out, setup, sum(r.status == 1 for r in results)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=40, help="LBO samples to solve (default 40)")
    ap.add_argument("--test2", type=int, default=None, help="test-2 samples (default samples/10, the paper's mix)")
    ap.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    ap.add_argument("--profile", type=int, default=2, help="samples profiled in-process (default 2; 0 = skip)")
    ap.add_argument("--alpha", type=float, default=0.0, help="force magnitude (N); default: calibrate to 30 mm")
    ap.add_argument("--store", default=None, help="store path (default: a temporary folder)")
    args = ap.parse_args()
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("tissuecast.fem").setLevel(logging.WARNING)

    from tissuecast.config import Config, with_overrides
    from tissuecast.dataset import simulate

    n2 = args.samples // 10 if args.test2 is None else args.test2
    cfg = with_overrides(Config(), dataset={"n_samples": args.samples, "n_test2": n2, "workers": args.workers,
                                            "alpha": args.alpha})
    store = Path(args.store) if args.store else Path(tempfile.mkdtemp(prefix="tc-throughput-")) / "bench.zarr"
    t = time.perf_counter()
    s = simulate(cfg, store, progress=True)
    wall = time.perf_counter() - t
    run, tm = s["run"], s["timing"]
    cal = s["calibration"]
    rate = run["sample_phase_samples_per_minute"]
    projected = run["calibration_seconds"] / 60.0 + (PAPER_SAMPLES / rate if rate else float("inf"))
    print(f"\ndata-set throughput: phantom {s['n_vertices']} vertices, P2, {run['executor']}, store {store}")
    print(f"  calibration: {len(cal['rounds'])} rounds x {len(cal.get('pilots', []))} pilots, "
          f"{run['calibration_seconds']:.1f} s, alpha = {cal['alpha']:.5g} N")
    print(f"  samples: {run['sample_phase_samples']} in {run['sample_phase_seconds']:.1f} s -> {rate:.2f} samples/min "
          f"({s['totals']['done']} done, {s['totals']['failed']} failed in the store; wall {wall:.1f} s)")
    print(f"  per sample: {tm['seconds_mean']:.2f} s worker time (max {tm['seconds_max']:.2f}), "
          f"{tm['increments_mean']:.1f} increments, {tm['iterations_mean']:.1f} iterations")
    md = s["max_displacement"]
    if md:
        print(f"  per-sample max displacement (mm): median {md['median']:.1f}, p90 {md['p90']:.1f}, max {md['max']:.1f}")
    io = run["parent_io_seconds"] / max(run["sample_phase_samples"], 1)
    print(f"  parent I/O: {1000 * io:.1f} ms per sample ({100 * run['parent_io_seconds'] / max(run['sample_phase_seconds'], 1e-9):.1f} % of the sample phase)")
    print(f"projected full paper data set ({PAPER_SAMPLES} samples): {projected:.1f} min "
          f"= {projected / TARGET_MINUTES:.2f} x the {TARGET_MINUTES:.0f}-minute target")
    if args.profile:
        buckets, setup, ok = _profile(cfg, cal["alpha"], args.profile)
        total = sum(buckets.values())
        print(f"where a worker's time goes ({args.profile} samples in-process, {ok} converged, "
              f"{total:.1f} s; per-process solver set-up {setup:.2f} s, paid once per worker):")
        for label, sec in buckets.items():
            print(f"  {label:<26} {sec:8.2f} s  {100 * sec / total if total else 0:5.1f} %")


if __name__ == "__main__":
    main()
