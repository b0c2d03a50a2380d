"""``tissuecast simulate [CONFIG|STORE]``: create or continue a data set of FEM samples."""

from __future__ import annotations

from ..evaluate import json_output
from ..config import with_overrides
from .help_examples import with_examples


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast simulate quick",
     "the preset's data set into its store (run it again to continue a stopped one)"),
    ("tissuecast simulate my_patient.toml --samples 400 --workers 2",
     "a smaller set first, on two worker processes"),
    ("tissuecast simulate runs/quick/dataset.zarr",
     "continue a store with the config it was made with"),
)


def register(sub) -> None:
    p = sub.add_parser(
        "simulate", help="create or continue a data set of nonlinear FEM samples (resumable)",
        description="Solve the LBO training samples (split train/valid/test1) and the test-2 samples the config "
                    "describes into a Zarr store. Re-running the same command continues an interrupted run; "
                    "the result is identical to an uninterrupted one.",
        **with_examples(*EXAMPLES))
    p.add_argument("config", nargs="?", help="TOML config file or a packaged preset (embedded, paper, quick); omitted = "
                   "defaults (the paper's set-up); or a data-set store directory: continue it with its own config")
    p.add_argument("--store", help="store directory (default: dataset.store of the config)")
    p.add_argument("--workers", type=int, help="local worker processes (default: dataset.workers; 0 = one per usable CPU)")
    p.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT (default: dataset.scheduler)")
    p.add_argument("--samples", type=int, help="number of LBO samples (overrides dataset.n_samples)")
    p.add_argument("--test2", type=int, help="number of test-2 samples (overrides dataset.n_test2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..dataset import simulate
    from .dataset_cmd import print_summary

    from ..app.pipeline import resolve_source

    cfg, store = resolve_source(args.config, args.store)
    overrides = {}
    if args.samples is not None:
        overrides["n_samples"] = args.samples
    if args.test2 is not None:
        overrides["n_test2"] = args.test2
    if args.workers is not None:
        overrides["workers"] = args.workers
    if args.scheduler is not None:
        overrides["scheduler"] = args.scheduler
    if overrides:
        cfg = with_overrides(cfg, dataset=overrides)
    summary = simulate(cfg, store, progress=not args.no_progress)
    if args.json:
        print(json_output.dumps(summary, indent=2))
    else:
        print_summary(summary)
        run_ = summary["run"]
        print(f"this run: {run_['solved']} samples in {run_['seconds']:.1f} s "
              f"({run_['samples_per_minute']:.1f} samples/min) on {run_['executor']}")
    return 0
