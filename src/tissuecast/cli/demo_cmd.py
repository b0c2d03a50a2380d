"""``tissuecast demo``: the whole pipeline on the built-in phantom with the quick preset."""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the quick preset on the phantom: simulate, train, evaluate, report",
                       description="Runs a packaged preset (--preset; the quick one by default) on the built-in phantom; "
                                   "everything goes into --output.")
    p.add_argument("--output", default="tissuecast-demo", help="output folder (default ./tissuecast-demo)")
    p.add_argument("--preset", default="quick", help="packaged preset name (quick, paper or embedded; default quick)")
    p.add_argument("--workers", type=int, help="local FEM worker processes")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..config import with_overrides
    from ..app.pipeline import run_pipeline
    from ..app.presets import preset_config
    from .run_cmd import report_run

    out = Path(args.output)
    cfg = preset_config(args.preset)
    cfg = with_overrides(cfg, output=str(out), dataset={"store": str(out / "dataset.zarr")})
    print(f"tissuecast demo: preset {args.preset!r}, {cfg.dataset.n_samples} training-set samples + "
          f"{cfg.dataset.n_test2} test-2 samples on the phantom; output in {out}", flush=True)
    result = run_pipeline(cfg, progress=not args.no_progress, workers=args.workers)
    report_run(result)
    return 0
