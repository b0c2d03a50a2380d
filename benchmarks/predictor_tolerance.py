"""The reduced-order predictor's hyper-reduction tolerance against the cost of a sample, side by side.

For a finished data set (a store with a reduced model), refits the reduced model on the
store's own snapshots at each ECSW tolerance (``dataset.predictor_tolerance``) and solves the
same samples in batches, as a worker does (one process, single-threaded BLAS, CPU time), with
each model in turn. Prints per tolerance: the sampled elements, the fit's time, the CPU time
of a prediction and of a whole sample, the full solver's Newton iterations and failures.
The first batch of each model is a warm-up and is not counted.

Usage::

    python benchmarks/predictor_tolerance.py STORE [--tolerances 0.01,0.02,0.04,0.08] [--batches 5] [--start 100]

The paper preset's figures (docs/scaling.md) came from ``runs/paper/dataset.zarr`` of
``tissuecast run configs/paper.toml``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"  # like a data-set worker: single-threaded BLAS

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def _timed(predict, totals: list):
    """``predict`` adding its CPU seconds and calls to ``totals`` ([seconds, calls])."""

    def timed(*a, **k):
        c = time.process_time()
        out = predict(*a, **k)
        totals[0] += time.process_time() - c
        totals[1] += 1
        return out

    return timed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store", help="a finished data set with a reduced model")
    ap.add_argument("--tolerances", default="0.01,0.02,0.04,0.08", help="ECSW tolerances, comma-separated")
    ap.add_argument("--batches", type=int, default=5, help="batches solved with each model (the first is a warm-up)")
    ap.add_argument("--batch-size", type=int, default=32, help="samples per batch (default 32, the paper preset's)")
    ap.add_argument("--start", type=int, default=100, help="first sample id solved (default 100)")
    args = ap.parse_args(argv)

    from tissuecast.dataset import recipe_from_store
    from tissuecast.dataset.batch import solve_batch_tasks
    from tissuecast.dataset.executors import single_threaded_blas
    from tissuecast.dataset.store import StoreWriter
    from tissuecast.dataset.worker import Task, context_for
    from tissuecast.fem.reduced import ReducedModel

    single_threaded_blas()
    writer = StoreWriter.open(args.store)
    if writer.reduced is None:
        raise SystemExit(f"{args.store} has no reduced model: make the data set with dataset.predictor = 'reduced'")
    base = recipe_from_store(writer)
    problem, snaps = base.problem(), writer.read("reduced/snapshots")
    alpha = float(writer.calibration["alpha"])
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    bs = args.batch_size
    ids = range(args.start, args.start + args.batches * bs)
    batches = [[Task(i, int(seeds[i]), float(betas[i]), alpha) for i in ids[k * bs:(k + 1) * bs]]
               for k in range(args.batches)]
    print(f"{args.store}: {len(snaps)} snapshots; samples {args.start}-{args.start + args.batches * bs - 1}, "
          f"batches of {bs}, first batch a warm-up\n")
    print("tolerance  elements  fit s  prediction ms  sample CPU s  Newton it  failed")
    for tol in [float(t) for t in args.tolerances.split(",")]:
        t = time.perf_counter()
        model = ReducedModel.fit(problem, snaps, tolerance=tol)
        fit = time.perf_counter() - t
        recipe = dataclasses.replace(base, reduced_basis=model.basis, reduced_elements=model.elements,
                                     reduced_weights=model.weights)
        solve_batch_tasks(recipe, batches[0])
        reduced = context_for(recipe).reduced
        predict_cpu = [0.0, 0]
        reduced.predict = _timed(reduced.predict, predict_cpu)
        c = time.process_time()
        results = [r for b in batches[1:] for r in solve_batch_tasks(recipe, b)]
        cpu = (time.process_time() - c) / max(len(results), 1)
        its = np.mean([r.iterations for r in results])
        failed = sum(int(r.status) != 1 for r in results)
        print(f"{tol:9.3g}  {len(model.elements):8d}  {fit:5.1f}  {1e3 * predict_cpu[0] / max(predict_cpu[1], 1):13.1f}  "
              f"{cpu:12.4f}  {its:9.2f}  {failed:6d}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
