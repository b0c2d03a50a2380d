"""Batched data generation: per-sample worker time, one at a time against batches, side by side.

The paper preset on the built-in phantom (P2, E = 21 kPa, nu = 0.45, alpha calibrated to
30 mm, the reduced-model predictor on its 40 basis samples): ``simulate`` builds a store up to
the end of the predictor phase (calibration + basis samples + fit, on ``--workers`` workers,
timed); then the same ``--samples`` further samples of the plan's seed stream are solved
in this process as one worker solves them (single-threaded BLAS), chunk by chunk, each chunk
once alone per sample (``dataset.batch_size = 1``: ``solve_task``) and once as a batch
(``solve_batch_tasks``), alternating so that load on a shared machine hits both alike. It
prints per-sample CPU and wall seconds, Newton iterations, factorisations and the largest
difference of the two answers for each batch size, and the ratio; then a projection of the
whole paper preset (2200 samples, mesh to model) with each batch size:

    calibration + predictor (measured wall) + (2200 - done) x CPU per sample / workers + training

with the training time given by ``--train-seconds`` (measure it with ``tissuecast train``).

Usage::

    python benchmarks/batching.py [--samples 96] [--batch 4,8,16] [--workers 2] [--train-seconds 45]

Run it on an idle machine for figures to quote; on a shared one the CPU columns are the ones
to compare.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"  # this process solves like a worker: single-threaded BLAS

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

PAPER_SAMPLES = 2000 + 200
TARGET_MINUTES = 5.0


def _timed(fn):
    c, w = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c, time.perf_counter() - w


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=96, help="samples solved with each batch size (default 96)")
    ap.add_argument("--batch", default="8", help="batch sizes compared with 1, comma-separated (default 8)")
    ap.add_argument("--workers", type=int, default=2, help="workers of the calibration and predictor phases")
    ap.add_argument("--train-seconds", type=float, default=45.0, help="training time added to the projection, s")
    args = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("tissuecast.fem").setLevel(logging.WARNING)

    from tissuecast.config import Config, with_overrides
    from tissuecast.dataset import SampleStatus, recipe_from_store, simulate
    from tissuecast.dataset.batch import solve_batch_tasks
    from tissuecast.dataset.executors import single_threaded_blas
    from tissuecast.dataset.sample_plan import sample_seed
    from tissuecast.dataset.store import StoreWriter
    from tissuecast.dataset.worker import Task, context_for, solve_task

    sizes = [int(b) for b in args.batch.split(",")]
    base = Config()
    n_basis = base.dataset.predictor_samples
    cfg = with_overrides(base, dataset={"n_samples": n_basis, "n_test2": 0, "workers": args.workers})
    store = Path(tempfile.mkdtemp(prefix="tc-batching-")) / "bench.zarr"
    t = time.perf_counter()
    s = simulate(cfg, store, progress=False)
    fixed_wall = time.perf_counter() - t
    print(f"\ncalibration + predictor ({s['calibration']['rounds'].__len__()} rounds, {n_basis} basis samples, "
          f"{args.workers} workers): {fixed_wall:.1f} s wall; store {store}", flush=True)

    single_threaded_blas()
    writer = StoreWriter.open(store)
    recipe = recipe_from_store(writer)
    alpha = float(writer.calibration["alpha"])
    ctx, setup_cpu, _ = _timed(lambda: context_for(recipe))
    ctx.solver(0).reference_factor()
    tasks = [Task(n_basis + k, int(sample_seed(cfg.dataset.seed, n_basis + k)), float("nan"), alpha)
             for k in range(args.samples)]
    rows = {1: [], **{b: [] for b in sizes}}
    answers = {1: {}, **{b: {} for b in sizes}}
    chunk = max(sizes)
    for lo in range(0, len(tasks), chunk):
        part = tasks[lo : lo + chunk]
        results, cpu, wall = _timed(lambda part=part: [solve_task(recipe, t) for t in part])
        rows[1].append((len(part), cpu, wall, results))
        for b in sizes:
            for k in range(0, len(part), b):
                sub = part[k : k + b]
                results, cpu, wall = _timed(lambda sub=sub: solve_batch_tasks(recipe, sub))
                rows[b].append((len(sub), cpu, wall, results))
        print(f"  {lo + len(part)}/{len(tasks)} samples", flush=True)
    for b, rs in rows.items():
        for _, _, _, results in rs:
            answers[b].update({r.index: r for r in results})

    def figures(b):
        rs = rows[b]
        n = sum(r[0] for r in rs)
        res = list(answers[b].values())
        done = [r for r in res if r.status == SampleStatus.DONE]
        return (sum(r[1] for r in rs) / n, sum(r[2] for r in rs) / n, np.mean([r.iterations for r in res]),
                np.mean([r.factorizations for r in res]), len(res) - len(done))

    print(f"\nper-sample worker time, paper preset on the phantom ({ctx.mesh.n_vertices} vertices, P2), {args.samples} "
          f"samples from the reduced model's predictions (worker set-up {setup_cpu:.1f} s CPU, once per process):")
    one = figures(1)
    for b in [1, *sizes]:
        cpu, wall, it, fac, failed = figures(b)
        diff = max((np.abs(answers[b][i].displacement - answers[1][i].displacement).max()
                    / max(np.abs(answers[1][i].displacement).max(), 1e-12)
                    for i in answers[1] if answers[1][i].status == SampleStatus.DONE
                    and answers[b][i].status == SampleStatus.DONE), default=float("nan"))
        minutes = (fixed_wall + (PAPER_SAMPLES - n_basis) * cpu / args.workers + args.train_seconds) / 60.0
        print(f"  batch {b:>3}: {cpu:6.3f} s CPU ({cpu / one[0]:.2f}x batch 1), {wall:6.3f} s wall, {it:5.1f} iterations, "
              f"{fac:4.2f} factorisations, {failed} failed, largest difference to batch 1 {diff:.1e} of the peak; "
              f"projected paper preset mesh -> model {minutes:.1f} min on {args.workers} workers "
              f"({minutes / TARGET_MINUTES:.2f}x the {TARGET_MINUTES:.0f}-minute target)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
