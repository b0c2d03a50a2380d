"""How the cost of a data set grows with the mesh: per-sample time, fill, memory, work vs dofs.

For each mesh (the phantom's surface re-meshed at finer sizes, and a brain-hemisphere-like
dome) and each linear-solver backend, side by side in one run, a child process:

1. meshes the shape with gmsh (meshes are generated, not shipped: gmsh's output differs
   between machines) and writes it to a temporary file;
2. runs ``tissuecast.dataset.simulate`` on it with the paper's set-up (P2, E = 21 kPa,
   nu = 0.45, 3 compact interior pins, alpha calibrated to q90 = 30 mm) but a small data set:
   ``--pilots`` calibration pilots, ``--basis`` reduced-model basis samples, ``--extra``
   samples started from the prediction, ``--workers`` local workers;
3. re-solves ``--resolve`` of the predicted samples in-process, once as in the data set
   (from the prediction) and once from zero, measuring CPU time (``time.process_time``,
   robust to other jobs on the machine), Newton iterations, preconditioner applications
   ("solves") and factorisations;
4. measures the fill of the reference factorisation: nnz(L) of the CHOLMOD factor, or of the
   coarse (vertex) factor of the p-multigrid cycle; and the peak resident memory of the
   data-set worker processes.

The table gives every figure against the free degrees of freedom; the exponent ``b`` of
``seconds ~ dofs^b`` is fitted (least squares in log-log) per backend over the meshes, for the
predicted samples, the samples from zero, and the per-sample CPU time of a paper-size data
set (2200 samples: 24 pilots per calibration round, as many rounds as measured, and 16 more
basis samples counted at the from-zero rate, the rest at the predicted rate). The wall-clock
projection of that data set (phases as measured, the rest at the predicted samples' worker
seconds on ``--workers`` workers) is printed too; on a machine shared with other jobs it is
inflated, and the CPU-time columns are the ones to compare.

Usage::

    python benchmarks/scaling.py [--meshes phantom:1.0,phantom:0.75,phantom:0.55,phantom:0.46,dome:3.0]
        [--backends p-multigrid,cholmod] [--pilots 4] [--basis 10] [--extra 6] [--resolve 3] [--workers 2]

``phantom:S`` is the phantom meshed at S times its element sizes (1.0 ~ 1170 vertices, 0.46
~ 10 000); ``dome:H`` the dome at H mm (3.0 ~ 3500 vertices, 2.1 ~ 10 000). ``--quick`` runs
phantom:1.0, phantom:0.75 and dome:4.5 with fewer samples.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"  # like a data-set worker: single-threaded BLAS

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

PAPER_SAMPLES = 2200
#: Solves of a paper-size data set before the predictor exists (24 pilots per calibration
#: round, 16 more basis samples), all counted as from zero in the CPU projection (an upper bound).
PAPER_PILOTS, PAPER_EXTRA_BASIS = 24, 16
DEFAULT_MESHES = "phantom:1.0,phantom:0.75,phantom:0.55,phantom:0.46,dome:3.0"
QUICK_MESHES = "phantom:1.0,phantom:0.75,dome:4.5"


def make_mesh(spec: str):
    """A mesh from ``shape:size`` (see the module notes)."""
    from tissuecast.mesh.shapes import dome_mesh, phantom_mesh

    shape, _, size = spec.partition(":")
    if shape == "phantom":
        return phantom_mesh(float(size or 1.0))
    if shape == "dome":
        return dome_mesh(float(size or 3.0))
    raise SystemExit(f"unknown mesh {spec!r}: use phantom:SCALE or dome:SIZE_MM")


def _fill(solver) -> tuple[str, int]:
    """(what, nnz) of the reference factorisation's triangular factor."""
    ref = solver.reference_factor()
    if getattr(ref, "exact", True):
        return "L", int(ref._factor.L().nnz) if hasattr(ref, "_factor") else -1
    coarse = ref._coarse
    return "L coarse", int(coarse.L().nnz) if coarse is not None else -1


def child(spec: str, backend: str, args) -> dict:
    """Everything measured for one mesh and backend (run in its own process)."""
    from tissuecast.config import Config, with_overrides
    from tissuecast.dataset import InitialGuess, SampleStatus, open_dataset, recipe_from_store, simulate
    from tissuecast.dataset.store import StoreWriter
    from tissuecast.dataset.worker import Task, context_for
    from tissuecast.mesh import write_mesh

    folder = Path(tempfile.mkdtemp(prefix="tc-scaling-"))
    t = time.process_time()
    mesh = make_mesh(spec)
    mesh_seconds = time.process_time() - t
    write_mesh(folder / "mesh.vtu", mesh)
    n_samples = args.basis + args.extra
    cfg = with_overrides(Config(), mesh={"path": str(folder / "mesh.vtu")}, solver={"linear_solver": backend},
                         dataset={"n_samples": n_samples, "n_test2": 0, "workers": args.workers,
                                  "calibration_samples": args.pilots, "predictor_samples": args.basis,
                                  "split": [1.0, 0.0, 0.0]})
    store = folder / "set.zarr"
    t = time.perf_counter()
    summary = simulate(cfg, store, progress=False)
    wall = time.perf_counter() - t
    worker_rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0  # MB (Linux: kB)
    run = summary["run"]
    ds = open_dataset(store)
    predicted = np.flatnonzero((ds.status == SampleStatus.DONE) & (ds.predicted == InitialGuess.REDUCED_MODEL))
    # in-process: solver set-up, fill, then the same samples from the prediction and from zero
    writer = StoreWriter.open(store)
    recipe = recipe_from_store(writer)
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    alpha = float(writer.calibration["alpha"])
    t = time.process_time()
    ctx = context_for(recipe)
    solver = ctx.solver(0)
    solver.reference_factor()
    setup = time.process_time() - t
    what, nnz = _fill(solver)
    warm, cold = [], []
    for i in predicted[: args.resolve]:
        inputs = ctx.inputs(Task(int(i), int(seeds[i]), float(betas[i]), alpha))
        forces = inputs.surface
        t = time.process_time()
        guess = ctx.reduced.predict(inputs.loads)
        res = solver.solve(forces, initial_guess=guess, **inputs.solve_keywords())
        warm.append((time.process_time() - t, res.iterations, res.solves, res.factorizations))
        t = time.process_time()
        res0 = solver.solve(forces, **inputs.solve_keywords())
        cold.append((time.process_time() - t, res0.iterations, res0.solves, res0.factorizations))
    sample_wall = float(np.median(ds.seconds[predicted])) if len(predicted) else float("nan")
    before = int(run["solved"] - run["sample_phase_samples"])
    fixed = run["calibration_seconds"] + run.get("reduced_seconds", 0.0)
    projected = fixed + (PAPER_SAMPLES - before) * sample_wall / args.workers
    return {
        "mesh": spec, "requested": backend, "backend": solver.linear.name, "vertices": mesh.n_vertices, "tets": mesh.n_tets,
        "dofs": solver.assembler.n_free, "mesh_seconds": mesh_seconds, "fill": what, "nnz": nnz, "setup_cpu": setup,
        "warm": np.mean(warm, axis=0).tolist() if warm else None, "cold": np.mean(cold, axis=0).tolist() if cold else None,
        "calibration_rounds": len(summary["calibration"]["rounds"]), "calibration_seconds": run["calibration_seconds"],
        "reduced_seconds": run.get("reduced_seconds", 0.0), "sample_wall": sample_wall, "failed": summary["totals"]["failed"],
        "peak_mm": summary["max_displacement"]["max"] if summary["max_displacement"] else float("nan"),
        "worker_rss_mb": worker_rss, "projected_minutes": projected / 60.0, "per_sample_projected": projected / PAPER_SAMPLES,
        "wall": wall, "slow": len(run["slow_samples"]),
    }


def _paper_cpu(r: dict) -> float:
    """CPU seconds per sample of a paper-size data set: the calibration rounds (as many as
    measured) and the extra basis samples at the from-zero rate, the rest at the predicted rate."""
    if not r["warm"] or not r["cold"]:
        return float("nan")
    fixed = PAPER_PILOTS * max(r["calibration_rounds"], 1) + PAPER_EXTRA_BASIS
    return (fixed * r["cold"][0] + (PAPER_SAMPLES - fixed) * r["warm"][0]) / PAPER_SAMPLES


def _exponent(dofs, seconds) -> float:
    x, y = np.log(np.asarray(dofs, float)), np.log(np.asarray(seconds, float))
    ok = np.isfinite(y)
    return float(np.polyfit(x[ok], y[ok], 1)[0]) if ok.sum() >= 2 else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", default=None, help=f"comma-separated shape:size list (default {DEFAULT_MESHES})")
    ap.add_argument("--backends", default="p-multigrid,cholmod",
                    help="linear solvers side by side (solver.linear_solver; 'auto' = the default choice by size)")
    ap.add_argument("--pilots", type=int, default=4, help="calibration pilots (dataset.calibration_samples)")
    ap.add_argument("--basis", type=int, default=10, help="reduced-model basis samples (dataset.predictor_samples)")
    ap.add_argument("--extra", type=int, default=6, help="samples solved from the prediction")
    ap.add_argument("--resolve", type=int, default=3, help="predicted samples re-solved in-process (CPU time)")
    ap.add_argument("--workers", type=int, default=2, help="data-set worker processes")
    ap.add_argument("--quick", action="store_true", help=f"meshes {QUICK_MESHES}, 3 pilots, 8 + 4 samples")
    ap.add_argument("--child", nargs=2, metavar=("MESH", "BACKEND"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        import logging

        logging.basicConfig(level=logging.WARNING)
        print("RESULT " + json.dumps(child(*args.child, args)), flush=True)
        return 0
    if args.quick:
        args.pilots, args.basis, args.extra, args.resolve = 3, 8, 4, 2
    meshes = (args.meshes or (QUICK_MESHES if args.quick else DEFAULT_MESHES)).split(",")
    backends = args.backends.split(",")
    rows = []
    opts = ["--pilots", str(args.pilots), "--basis", str(args.basis), "--extra", str(args.extra), "--resolve",
            str(args.resolve), "--workers", str(args.workers)]
    for spec in meshes:
        for backend in backends:
            t = time.perf_counter()
            out = subprocess.run([sys.executable, __file__, "--child", spec, backend, *opts], capture_output=True,
                                 text=True)
            line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
            if out.returncode or not line:
                print(f"{spec} {backend}: failed after {time.perf_counter() - t:.0f} s\n{out.stderr[-2000:]}", flush=True)
                continue
            r = json.loads(line[0][7:])
            rows.append(r)
            w, c = r["warm"] or [np.nan] * 4, r["cold"] or [np.nan] * 4
            backend = r["requested"] + (" (" + r["backend"] + ")" if r["requested"] == "auto" else "")
            print(f"{spec:<13} {backend:<11} {r['vertices']:>6} v {r['dofs']:>7} dofs  {r['fill']} {r['nnz'] / 1e6:6.1f}M  "
                  f"setup {r['setup_cpu']:6.2f} s  predicted {w[0]:6.2f} s CPU "
                  f"({w[1]:.1f} it, {w[2]:.0f} solves, {w[3]:.1f} fac)  "
                  f"from zero {c[0]:7.2f} s CPU ({c[1]:.0f} it, {c[2]:.0f} solves, {c[3]:.1f} fac)  "
                  f"calibration {r['calibration_seconds']:.0f} s ({r['calibration_rounds']} rounds)  "
                  f"basis {r['reduced_seconds']:.0f} s  "
                  f"worker RSS {r['worker_rss_mb']:.0f} MB  paper-size set {_paper_cpu(r):.2f} s CPU/sample, "
                  f"{r['projected_minutes']:.0f} min wall on {args.workers} workers  "
                  f"[{r['failed']} failed, {r['slow']} slow, peak {r['peak_mm']:.1f} mm, run {r['wall']:.0f} s]", flush=True)
    print("\nfitted exponent b of seconds ~ dofs^b (least squares, log-log), per backend:")
    for backend in dict.fromkeys(r["requested"] for r in rows):
        sel = [r for r in rows if r["requested"] == backend]
        dofs = [r["dofs"] for r in sel]
        fits = {
            "predicted sample (CPU)": _exponent(dofs, [(r["warm"] or [np.nan])[0] for r in sel]),
            "sample from zero (CPU)": _exponent(dofs, [(r["cold"] or [np.nan])[0] for r in sel]),
            "per sample, paper-size set (CPU)": _exponent(dofs, [_paper_cpu(r) for r in sel]),
            "fill nnz": _exponent(dofs, [max(r["nnz"], 1) for r in sel]),
            "worker RSS": _exponent(dofs, [r["worker_rss_mb"] for r in sel]),
        }
        span = f"{min(dofs)}-{max(dofs)} dofs, {len(sel)} meshes"
        print(f"  {backend:<11} ({span}): " + ", ".join(f"{k} {v:.2f}" for k, v in fits.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
