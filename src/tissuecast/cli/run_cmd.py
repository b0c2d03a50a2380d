"""``tissuecast run CONFIG``: the whole pipeline, simulate -> train -> evaluate -> report."""

from __future__ import annotations

from .help_examples import with_examples


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast run quick",
     "a packaged preset: the phantom, paper-style loads, a few minutes on 2 cores"),
    ("tissuecast run embedded --workers 2",
     "the clinical preset (attached region, elastic support, gravity, a tracked retractor)"),
    ("tissuecast run my_patient.toml --skip-simulate",
     "train and evaluate again on the store the config names, as it is"),
)


def register(sub) -> None:
    p = sub.add_parser("run", help="run the whole pipeline as a config describes",
                       description="Simulate the data set (resumable), train the surrogate, evaluate it and write the "
                                   "report. Paths: dataset.store, and in the config's output folder model/ and "
                                   "<evaluate.output>/.", **with_examples(*EXAMPLES))
    p.add_argument("config", help="TOML config file (e.g. configs/paper.toml), or the name of a packaged preset "
                                  "(quick, paper, embedded)")
    p.add_argument("--skip-simulate", action="store_true", help="use the existing store as it is")
    p.add_argument("--workers", type=int, help="local FEM worker processes (default: dataset.workers; 0 = one per usable CPU)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def report_run(result) -> None:
    """Print the outcome of :func:`~tissuecast.app.pipeline.run_pipeline`."""
    from ..evaluate.report import format_evaluation

    p = result["paths"]
    ds = result["dataset"]
    if ds:
        tot = ds.get("totals", {})
        print(f"data set {p.store}: {tot.get('done', '?')} done, {tot.get('failed', '?')} failed")
    if result.get("nominal_dataset"):
        tot = result["nominal_dataset"].get("totals", {})
        print(f"nominal expert's data set {p.nominal_store}: {tot.get('done', '?')} done, {tot.get('failed', '?')} failed")
    sec = result["seconds"]
    print("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in sec.items()))
    print(format_evaluation(result["evaluation"]))
    print(f"model:  {p.model}")
    print(f"report: {result['report']}")


def run(args) -> int:
    from ..app.configuration import load_run_config
    from ..app.pipeline import run_pipeline

    cfg = load_run_config(args.config)
    result = run_pipeline(cfg, simulate=not args.skip_simulate, progress=not args.no_progress, workers=args.workers)
    report_run(result)
    return 0
