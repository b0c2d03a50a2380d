"""Data-set generation throughput on the paper-size phantom (P2), and where the time goes.

Runs ``tissuecast.dataset.simulate`` on the built-in phantom with the paper's set-up (P2,
E = 21 kPa, nu = 0.45, 3 fixed interior vertices, 20 LBO modes, alpha calibrated to 30 mm)
for a small data set in the paper's LBO : test-2 mix, then prints

* samples per minute (sample phase, after calibration) and the calibration's fixed cost,
* the projected time of the full paper data set (2000 LBO + 200 test-2) and its ratio to
  the 15-minute target,
* with the reduced-model predictor (the default): its fixed cost (the first samples solved
  from zero, the fit) and the per-sample figures of samples solved from zero and from the
  prediction,
* parent-process I/O per sample, and a cProfile split of one worker's solve time into
  tangent assembly, residual/energy assembly, factorisation, triangular solves, the
  reduced-model prediction and the rest,
* side by side: the same samples solved again as in the data set and from zero (seconds,
  iterations, factorisations, and how far apart the two solutions are).

Usage::

    python benchmarks/dataset_throughput.py [--samples 120] [--workers 2] [--profile 6] [--alpha A] [--predictor reduced|none]

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
    ("residual/energy assembly",
     lambda f, n: f.endswith("assembly.py") and n in ("energy_and_force", "internal_force", "energy")),
    ("factorisation", lambda f, n: f.replace("\\", "/").endswith("fem/linear/direct.py") and n == "factorize"),
    ("triangular solves", lambda f, n: f.replace("\\", "/").endswith("fem/linear/direct.py") and n == "solve"),
    ("reduced-model prediction", lambda f, n: f.endswith("reduced.py") and n == "predict"),
]


def _profile(store: Path, indices) -> tuple[dict, float, list]:
    """Solve the stored samples ``indices`` again in this process, as a worker would (with the
    store's reduced-model predictor, if any), under cProfile; then each one from zero too.

    Returns the seconds per bucket of the worker solves, the per-process set-up seconds, and
    per sample (warm seconds, cold seconds, warm iterations, cold iterations, warm
    factorisations, cold factorisations, max vertex difference / peak).
    """
    import numpy as np

    from tissuecast.dataset import SampleStatus, recipe_from_store
    from tissuecast.dataset.store import StoreWriter
    from tissuecast.dataset.worker import Task, context_for, solve_task

    writer = StoreWriter.open(store)
    recipe = recipe_from_store(writer)
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    alpha = float(writer.calibration["alpha"])
    t = time.perf_counter()
    ctx = context_for(recipe)
    ctx.solver(0)
    setup = time.perf_counter() - t
    tasks = [Task(int(i), int(seeds[i]), float(betas[i]), alpha) for i in indices]
    prof = cProfile.Profile()
    prof.enable()
    results = [solve_task(recipe, task) for task in tasks]
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = sum(r.seconds for r in results)
    out = {}
    for label, pred in _BUCKETS:
        # cumulative time, counting the assembly calls the reduced model makes in its own bucket
        out[label] = sum(ct for (f, _, n), v in stats.items() if pred(f, n)
                         for (cf, _, cn), (_, _, _, ct) in v[4].items()
                         if label.startswith("reduced") or not cf.endswith("reduced.py"))
    out["other"] = max(total - sum(out.values()), 0.0)
    pairs = []
    for task, warm in zip(tasks, results):
        inputs = ctx.inputs(task)
        t = time.perf_counter()
        cold = ctx.solver(0).solve(inputs.surface, **inputs.solve_keywords())
        sec = time.perf_counter() - t
        peak = float(np.abs(cold.displacement).max())
        diff = (float(np.abs(warm.displacement - cold.displacement).max()) / peak
                if warm.status == SampleStatus.DONE else float("nan"))
        pairs.append((warm.seconds, sec, warm.iterations, cold.iterations, warm.factorizations, cold.factorizations,
                      diff, warm.predicted))
    return out, setup, pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=120, help="LBO samples to solve (default 120)")
    ap.add_argument("--test2", type=int, default=None, help="test-2 samples (default samples/10, the paper's mix)")
    ap.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    ap.add_argument("--profile", type=int, default=6, help="samples profiled in-process (default 6; 0 = skip)")
    ap.add_argument("--alpha", type=float, default=0.0, help="force magnitude (N); default: calibrate to 30 mm")
    ap.add_argument("--store", default=None, help="store path (default: a temporary folder)")
    ap.add_argument("--predictor", default="reduced", choices=("reduced", "none"),
                    help="initial guesses (dataset.predictor; default reduced)")
    args = ap.parse_args()
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("tissuecast.fem").setLevel(logging.WARNING)

    from tissuecast.config import Config, with_overrides
    from tissuecast.dataset import simulate

    n2 = args.samples // 10 if args.test2 is None else args.test2
    cfg = with_overrides(Config(), dataset={"n_samples": args.samples, "n_test2": n2, "workers": args.workers,
                                            "alpha": args.alpha, "predictor": args.predictor})
    store = Path(args.store) if args.store else Path(tempfile.mkdtemp(prefix="tc-throughput-")) / "bench.zarr"
    t = time.perf_counter()
    s = simulate(cfg, store, progress=True)
    wall = time.perf_counter() - t
    run, tm = s["run"], s["timing"]
    cal = s["calibration"]
    rate = run["sample_phase_samples_per_minute"]
    before = run["solved"] - run["sample_phase_samples"]  # pilots and reduced-model samples
    fixed_cost = run["calibration_seconds"] + run.get("reduced_seconds", 0.0)
    projected = fixed_cost / 60.0 + ((PAPER_SAMPLES - before) / rate if rate else float("inf"))
    print(f"\ndata-set throughput: phantom {s['n_vertices']} vertices, P2, {run['executor']}, store {store}")
    print(f"  calibration: {len(cal['rounds'])} rounds x {len(cal.get('pilots', []))} pilots, "
          f"{run['calibration_seconds']:.1f} s, alpha = {cal['alpha']:.5g} N")
    print(f"  samples: {run['sample_phase_samples']} in {run['sample_phase_seconds']:.1f} s -> {rate:.2f} samples/min "
          f"({s['totals']['done']} done, {s['totals']['failed']} failed in the store; wall {wall:.1f} s)")
    print(f"  per sample: {tm['seconds_mean']:.2f} s worker time (max {tm['seconds_max']:.2f}), "
          f"{tm['increments_mean']:.1f} increments, {tm['iterations_mean']:.1f} iterations")
    pr = s["predictor"]
    if pr["model"]:
        m = pr["model"]
        print(f"  reduced-model predictor: {m['snapshots']} samples from zero + fit = "
              f"{run.get('reduced_seconds', 0.0):.1f} s (fixed cost); {m['modes']} modes, {m['elements']} ECSW elements")
        for key in ("from_zero", "from_previous_round", "predicted", "prediction_failed"):
            st = pr[key]
            if st["samples"]:
                print(f"    {key:<18} {st['samples']:>5} samples: {st['seconds_mean']:.2f} s, "
                      f"{st['iterations_mean']:.1f} iterations, {st['factorizations_mean']:.1f} factorisations each")
    md = s["max_displacement"]
    if md:
        print(f"  per-sample max displacement (mm): median {md['median']:.1f}, p90 {md['p90']:.1f}, max {md['max']:.1f}")
    io = run["parent_io_seconds"] / max(run["sample_phase_samples"], 1)
    share = 100 * run["parent_io_seconds"] / max(run["sample_phase_seconds"], 1e-9)
    print(f"  parent I/O: {1000 * io:.1f} ms per sample ({share:.1f} % of the sample phase)")
    print(f"projected full paper data set ({PAPER_SAMPLES} samples): {projected:.1f} min "
          f"= {projected / TARGET_MINUTES:.2f} x the {TARGET_MINUTES:.0f}-minute target")
    if args.profile:
        import numpy as np

        from tissuecast.dataset import SampleStatus, open_dataset

        ds = open_dataset(store)
        later = np.flatnonzero((ds.status == SampleStatus.DONE) & (np.arange(len(ds)) >= cfg.dataset.predictor_samples))
        buckets, setup, pairs = _profile(store, later[: args.profile])
        total = sum(buckets.values())
        print(f"where a worker's time goes ({len(pairs)} samples in-process, {total:.1f} s; per-process solver "
              f"set-up {setup:.2f} s, paid once per worker):")
        for label, sec in buckets.items():
            print(f"  {label:<26} {sec:8.2f} s  {100 * sec / total if total else 0:5.1f} %")
        if pairs:
            p = np.array(pairs)
            print(f"side by side, the same {len(p)} samples solved as in the data set (predictor {args.predictor}) and "
                  "from zero:")
            print(f"  seconds      {p[:, 0].sum():7.1f} vs {p[:, 1].sum():7.1f}  -> {p[:, 1].sum() / p[:, 0].sum():.2f}x")
            print(f"  iterations   {p[:, 2].mean():7.1f} vs {p[:, 3].mean():7.1f} per sample")
            print(f"  factorisations {p[:, 4].mean():5.1f} vs {p[:, 5].mean():7.1f} per sample")
            print(f"  largest difference between the two solutions: {100 * np.nanmax(p[:, 6]):.3f} % of the peak "
                  f"displacement; {int((p[:, 7] == 1).sum())} of {len(p)} started from a prediction")

if __name__ == "__main__":
    main()
