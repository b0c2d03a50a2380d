"""Per-sample solve time of two configs' data sets, side by side in one run (issue 16's target:
configs/embedded.toml no worse than 1.5x the paper preset's).

Each config makes a small data set of ``--samples`` LBO samples (no test-2) through the data-
generation path itself (:func:`tissuecast.dataset.simulate`: calibration, reduced-order
predictor from ``--predictor-samples`` samples if the config uses one, retries), one worker
process each, the two runs one after the other in this process's machine state. The figures
are read back from the stores: median and mean seconds per sample (the solve alone, as
recorded per sample), Newton iterations and factorisations per sample, how many samples
started from the predictor, how many needed a retry (a second, more cautious attempt), and the
ratio B / A.

    python benchmarks/scenario_solve_time.py configs/paper.toml configs/embedded.toml
    python benchmarks/scenario_solve_time.py A.toml B.toml --samples 20 --keep runs/bench
    python benchmarks/scenario_solve_time.py configs/embedded.toml --nominal --samples 240
    python benchmarks/scenario_solve_time.py configs/embedded.toml --nominal --samples 120 --mesh brain

With ``--nominal`` one config is compared with itself at its nominal parameters (A: its
``[scenario.uncertain]`` ranges emptied, nothing drawn; B: as given): what the uncertain
parameters cost in time (the mismatch issue's target: at most 1.2x).

With ``--mesh`` both configs run on another mesh: a mesh file, or one of the organ shapes of
``benchmarks/organ_meshes.py`` (``brain``: the MNI left hemisphere at ``--brain-size`` mm, 3410
vertices at 7.5; it needs nilearn), built into ``--keep`` (or the temporary folder; a mesh file of
that name already there is used as it is). A config
with an instrument has its access point and patch radius fitted to the mesh as
``benchmarks/organ_speed.py`` does (:func:`organ_meshes.embedded_overrides`).

Timings of a shared machine are inflated by whatever else runs on it; take the figure on an
idle machine and compare the ratio of one run only. The ratio of Newton iterations and
factorisations per sample is printed beside it: counts, the same on any machine and load (the
seconds' ratio of one data set pair moves by about 0.05 from run to run).
"""

from __future__ import annotations

import os
import sys

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from tissuecast.config import load_config, nothing_drawn, with_overrides  # noqa: E402
from tissuecast.dataset import open_dataset, simulate  # noqa: E402
from tissuecast.dataset.codes import InitialGuess  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import organ_meshes  # noqa: E402


def time_config(path: str, samples: int, predictor_samples: int, folder: Path, nominal: bool = False,
                mesh: Path | None = None) -> dict:
    """Make the small data set of config ``path`` in ``folder`` and read its per-sample figures
    (``nominal``: with the config's uncertain parameters at their nominal values; ``mesh``: on
    this mesh file instead of the config's, an instrument's access fitted to it)."""
    cfg = load_config(path)
    dataset = {"n_samples": samples, "n_test2": 0, "calibration_samples": min(cfg.dataset.calibration_samples, 8),
               "predictor_samples": min(predictor_samples, max(2, samples - 2)), "workers": 1}
    over, scenario = {"dataset": dataset}, {"uncertain": nothing_drawn()} if nominal else {}
    if mesh is not None:
        over["mesh"] = {"path": str(mesh)}
        if cfg.scenario.indentation.enabled:
            scenario.update(organ_meshes.embedded_overrides(mesh, cfg))
    if scenario:
        over["scenario"] = scenario
    cfg = with_overrides(cfg, **over)
    label = " (nominal)" if nominal else ""
    store = folder / (Path(path).stem + ("-nominal" if nominal else "") + ".zarr")
    t0 = time.perf_counter()
    simulate(cfg, store, progress=False, workers=1)
    wall = time.perf_counter() - t0
    ds = open_dataset(store)
    done = ds.select(status="done")
    sec, its, fac = ds.seconds[done], ds.iterations[done], ds.factorizations[done]
    return {"config": path + label, "name": Path(path).stem + label,
            "scenario": cfg.scenario.name, "done": len(done), "of": len(ds), "median_s": float(np.median(sec)),
            "mean_s": float(np.mean(sec)), "iterations": float(np.mean(its)), "factorizations": float(np.mean(fac)),
            "predicted": int(np.sum(ds.predicted[done] == InitialGuess.REDUCED_MODEL)),
            "retried": int(np.sum(ds.attempts[done] > 1)),
            "peak": float(np.median(ds.max_displacement[done])),
            "wall": wall}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("baseline", help="config A (e.g. configs/paper.toml)")
    ap.add_argument("scenario", nargs="?", help="config B (e.g. configs/embedded.toml); with --nominal, not given")
    ap.add_argument("--nominal", action="store_true",
                    help="compare config A at its nominal parameters (its [scenario.uncertain] emptied) with A as given")
    ap.add_argument("--samples", type=int, default=20, help="LBO samples per data set (default 20)")
    ap.add_argument("--predictor-samples", type=int, default=8,
                    help="samples solved from zero that build the reduced-order predictor, if the config uses one "
                    "(default 8; the rest start from its prediction, as in data generation)")
    ap.add_argument("--keep", metavar="DIR", help="keep the two stores here (default: a temporary folder)")
    ap.add_argument("--mesh", default="", help="run both configs on this mesh: a mesh file or one of "
                    + ", ".join(m for m in organ_meshes.MESHES if m != "phantom") + " (built here; see the notes)")
    organ_meshes.add_size_arguments(ap)
    args = ap.parse_args(argv)
    if args.nominal == (args.scenario is not None):
        ap.error("give two configs, or one config and --nominal")
    if args.mesh and args.mesh not in organ_meshes.MESHES and not Path(args.mesh).is_file():
        ap.error(f"--mesh {args.mesh!r} is neither a mesh file nor one of {', '.join(organ_meshes.MESHES)}")
    pairs = ([(args.baseline, True), (args.baseline, False)] if args.nominal
             else [(args.baseline, False), (args.scenario, False)])
    with contextlib.ExitStack() as stack:  # a temporary folder is removed however the run ends
        folder = (Path(args.keep) if args.keep
                  else Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="tissuecast-solve-time-"))))
        folder.mkdir(parents=True, exist_ok=True)
        mesh = Path(args.mesh) if args.mesh else None
        if args.mesh in organ_meshes.MESHES:
            mesh, _ = organ_meshes.build([args.mesh], folder, args)[args.mesh]
        rows = [time_config(p, args.samples, args.predictor_samples, folder, nominal, mesh) for p, nominal in pairs]
    head = (f"{'config':<34} {'scenario':<12}{'done':>8}{'median s':>10}{'mean s':>9}{'Newton':>8}{'factor':>8}"
            f"{'predicted':>10}{'retried':>8}{'peak mm':>9}{'wall s':>8}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['config']:<34} {r['scenario']:<12}{r['done']:>4}/{r['of']:<3}{r['median_s']:>10.3f}{r['mean_s']:>9.3f}"
              f"{r['iterations']:>8.1f}{r['factorizations']:>8.1f}{r['predicted']:>10}{r['retried']:>8}{r['peak']:>9.2f}{r['wall']:>8.1f}")
    a, b = rows
    target = "the mismatch issue's target <= 1.2x" if args.nominal else "target <= 1.5x"
    print(f"ratio {b['name']} / {a['name']} per sample: median {b['median_s'] / a['median_s']:.2f}x, "
          f"mean {b['mean_s'] / a['mean_s']:.2f}x, wall {b['wall'] / a['wall']:.2f}x ({target}); seconds are each "
          "sample's solve as the store records it (calibration, predictor building and worker start-up are in 'wall')")
    counts = ", ".join(f"{what} {b[key] / a[key]:.2f}x" if a[key] else f"{what} {b[key]:.1f} against none"
                       for what, key in (("Newton iterations", "iterations"), ("factorisations", "factorizations")))
    print(f"per sample: {counts} (counts: the same on any machine under any load)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
