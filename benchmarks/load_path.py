"""Does a store hold the equilibria its loading reaches? Its samples solved again along the load path.

Some scenarios have more than one equilibrium under the same loads (a spring-held body whose
most compressed elements come close to a local instability, docs/scenarios.md). A solve that
starts at the full load from a guess (the reduced-order predictor's) can then land on another
one than the loading reaches from the undeformed state: the store's answer depends on the
solver's path, not only on the physics. This benchmark solves each chosen sample of a store
again from zero along its load path (the first increment ``--increment`` of the load, growing
as the solver converges), with each strategy of ``--strategies``, and reports per strategy:

- how many stored answers lie farther than ``--tolerance`` (a share of the sample's peak
  displacement) from the load path's, and the largest such distance (mm);
- how many samples the strategies' own load paths disagree on (a bifurcation on the way: the
  branch then depends on round-off);
- the time of a load-path solve (one sample alone, no batch) beside the store's own recorded
  seconds per sample.

    python benchmarks/load_path.py runs/embedded/dataset.zarr --samples 120
    python benchmarks/load_path.py STORE --first 40 --samples 120 --strategies krylov newton

Timings of a shared machine are inflated by whatever else runs on it.
"""

from __future__ import annotations

import os
import sys

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from tissuecast.dataset import open_dataset  # noqa: E402
from tissuecast.dataset.worker import Task, context_for  # noqa: E402
from tissuecast.errors import ConvergenceError  # noqa: E402


def load_path_solver(solver, strategy: str, increment: float):
    """A copy of ``solver`` (a :class:`tissuecast.fem.Solver` or a view of it) that solves
    with ``strategy`` from zero, its first increment ``increment`` of the load."""
    out = copy.copy(solver)
    out.config = dataclasses.replace(solver.config, strategy=strategy, initial_increment=increment)
    return out


def apart(u: np.ndarray, v: np.ndarray, tolerance: float) -> tuple[float, bool]:
    """The largest vertex distance (mm) between fields ``u`` and ``v`` ((n, 3) mm), and whether
    it is more than ``tolerance`` times ``v``'s peak displacement."""
    d = float(np.linalg.norm(u - v, axis=1).max())
    return d, d > tolerance * max(float(np.linalg.norm(v, axis=1).max()), 1e-12)


def path_answers(ds, samples, strategies, increment: float) -> dict:
    """Each of ``samples`` (ids) of the data set ``ds`` solved from zero along its load path with
    each strategy. Returns ``{strategy: {"fields": {id: (n, 3) mm}, "seconds": {id: s}, "failed": {id: why}}}``."""
    ctx = context_for(ds.recipe())
    base = ctx.solver(0)
    out = {s: {"fields": {}, "seconds": {}, "failed": {}} for s in strategies}
    for k in samples:
        k = int(k)
        inputs = ctx.inputs(Task(k, int(ds.seed[k]), float(ds.beta[k]), float(ds.alpha[k])))
        view = base.with_parameters(*inputs.solver_parameters) if inputs.parameters is not None else base
        for strategy in strategies:
            solver = load_path_solver(view, strategy, increment)
            t0 = time.perf_counter()
            try:
                res = solver.solve(inputs.surface, **inputs.solve_keywords())
            except ConvergenceError as exc:
                out[strategy]["failed"][k] = str(exc)
            else:
                out[strategy]["fields"][k] = np.asarray(res.displacement[: ds.mesh.n_vertices])
            out[strategy]["seconds"][k] = time.perf_counter() - t0
    return out


def compare(ds, answers: dict, tolerance: float) -> dict:
    """The figures of the module notes from :func:`path_answers`' ``answers`` of the data set ``ds``."""
    report = {"tolerance": tolerance, "strategies": {}}
    done = ds.select(status="done")
    stored_seconds = float(np.mean(ds.seconds[done])) if len(done) else float("nan")
    for strategy, a in answers.items():
        off, dist = [], []
        for k, u in a["fields"].items():
            d, far = apart(np.asarray(ds.displacements[k], dtype=np.float64), u, tolerance)
            dist.append(d)
            if far:
                off.append({"sample": k, "distance_mm": d, "peak_mm": float(np.linalg.norm(u, axis=1).max())})
        sec = np.array(list(a["seconds"].values()))
        report["strategies"][strategy] = {
            "solved": len(a["fields"]), "failed": len(a["failed"]), "off_path": len(off),
            "off_path_samples": sorted(off, key=lambda r: -r["distance_mm"]),
            "largest_distance_mm": max(dist, default=float("nan")),
            "seconds_mean": float(sec.mean()) if len(sec) else float("nan"),
            "seconds_median": float(np.median(sec)) if len(sec) else float("nan")}
    names = list(answers)
    if len(names) >= 2:
        a, b = answers[names[0]]["fields"], answers[names[1]]["fields"]
        both = sorted(set(a) & set(b))
        split = [k for k in both if apart(b[k], a[k], tolerance)[1]]
        report["paths_disagree"] = {"strategies": names[:2], "samples": split, "of": len(both)}
    report["stored_seconds_mean"] = stored_seconds
    return report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", help="a data set (zarr folder)")
    ap.add_argument("--first", type=int, default=0, help="first sample id (default 0)")
    ap.add_argument("--samples", type=int, default=40, help="how many samples from --first (default 40)")
    ap.add_argument("--strategies", nargs="+", default=["krylov", "newton"],
                    choices=["krylov", "newton", "quasi-newton"], help="load-path solvers (default krylov newton)")
    ap.add_argument("--increment", type=float, default=0.1, help="first load increment (default 0.1)")
    ap.add_argument("--tolerance", type=float, default=0.01,
                    help="off the path when farther than this share of the peak (default 0.01)")
    ap.add_argument("--json", metavar="FILE", help="also write the report here")
    args = ap.parse_args(argv)
    if not 0.0 < args.increment <= 1.0:
        ap.error(f"--increment must be in (0, 1], got {args.increment}")
    ds = open_dataset(args.store)
    done = ds.select(status="done")
    samples = [int(k) for k in done[(done >= args.first) & (done < args.first + args.samples)]]
    if not samples:
        ap.error(f"no solved samples in ids {args.first}..{args.first + args.samples - 1} of {args.store}")
    t0 = time.perf_counter()
    report = {"store": str(args.store),
              **compare(ds, path_answers(ds, samples, args.strategies, args.increment), args.tolerance)}
    print(f"{len(samples)} samples of {args.store}, each from zero along its load path (first increment "
          f"{args.increment:g}); off the path: farther than {100 * args.tolerance:g} % of the peak; "
          f"{time.perf_counter() - t0:.0f} s")
    print(f"{'strategy':<14}{'solved':>8}{'failed':>8}{'stored off':>12}{'largest mm':>12}{'s mean':>9}{'s median':>10}")
    for name, r in report["strategies"].items():
        print(f"{name:<14}{r['solved']:>8}{r['failed']:>8}{r['off_path']:>12}{r['largest_distance_mm']:>12.2f}"
              f"{r['seconds_mean']:>9.2f}{r['seconds_median']:>10.2f}")
    print(f"the store's own solves: {report['stored_seconds_mean']:.2f} s a sample (mean, as recorded)")
    if "paths_disagree" in report:
        p = report["paths_disagree"]
        print(f"the load paths of {p['strategies'][0]} and {p['strategies'][1]} disagree on {len(p['samples'])} of "
              f"{p['of']} samples {p['samples'][:10]} (a bifurcation on the way)")
    for name, r in report["strategies"].items():
        worst = ", ".join(f"{o['sample']} ({o['distance_mm']:.1f} of {o['peak_mm']:.1f} mm)" for o in r["off_path_samples"][:8])
        if worst:
            print(f"{name}: stored answers off its path: {worst}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
