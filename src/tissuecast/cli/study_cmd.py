"""``tissuecast study {architecture,markers,pca} CONFIG|STORE``: the paper's parametric studies (CSV + PNG);
``tissuecast study mismatch CONFIG --model LABEL=DIR ...``: what a mismatch between simulator and patient costs."""

from __future__ import annotations

from pathlib import Path

from ..evaluate.mismatch import DISCRETISATION_SAMPLES
from ..evaluate.studies import ARCHITECTURE_REPEATS, ARCHITECTURE_WIDTHS, MARKER_COUNTS, PCA_MAX_COMPONENTS
from .help_examples import with_examples

_WIDTHS = ",".join(str(w) for w in ARCHITECTURE_WIDTHS)
_COUNTS = f"{MARKER_COUNTS[0]}-{MARKER_COUNTS[-1]}"


def _ints(text: str) -> list[int]:
    """'3-20' or '32,64,128' -> list of ints."""
    out = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-", 1)
            out += list(range(int(a), int(b) + 1))
        elif part.strip():
            out.append(int(part))
    return out


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast study markers quick --counts 3,5,10",
     "test-1 accuracy against the number of markers"),
    ("tissuecast study mismatch embedded --model shipped=runs/embedded/model --samples 100",
     "the model on sets simulated with other tissue, supports or elements than it was trained for"),
)


def register(sub) -> None:
    p = sub.add_parser("study", help="studies: hidden layers, number of markers, PCA size; a model against mismatched "
                                     "simulations",
                       description="architecture, markers, pca: train on the store's train split and measure test-1 "
                                   "accuracy. mismatch: evaluate the models given as --model LABEL=FOLDER (at least "
                                   "one) on test sets simulated from the config with one thing changed (kept in "
                                   "OUT/mismatch, resumable). Each writes study_NAME.csv / .png (mismatch also .json) "
                                   "into --out (default: the report folder of the config's output), which `tissuecast "
                                   "evaluate` then includes in the report.", **with_examples(*EXAMPLES))
    p.add_argument("study", choices=("architecture", "markers", "pca", "mismatch"), help="which study")
    p.add_argument("source", nargs="?", help="TOML config file, a packaged preset or a data-set store directory")
    p.add_argument("--store", help="store directory (default: dataset.store of the config)")
    p.add_argument("--out", help="output folder (default: the report folder of the config)")
    p.add_argument("--widths", default=_WIDTHS, help=f"architecture: layer widths (default {_WIDTHS})")
    p.add_argument("--repeats", type=int, default=ARCHITECTURE_REPEATS,
                   help=f"architecture: trainings per architecture (default {ARCHITECTURE_REPEATS})")
    p.add_argument("--counts", default=_COUNTS, help=f"markers: numbers of markers (default {_COUNTS})")
    p.add_argument("--max-components", type=int, default=PCA_MAX_COMPONENTS,
                   help=f"pca: largest n_w (default {PCA_MAX_COMPONENTS})")
    p.add_argument("--model", action="append", default=[], metavar="LABEL=DIR",
                   help="mismatch: a model folder to evaluate, with its label (repeat: e.g. nominal=runs/a/model "
                        "uncertain=runs/b/model)")
    p.add_argument("--sets", default="",
                   help="mismatch: comma-separated set names (default: every set the scenario has but the refined "
                        "'discretisation', whose refined solves take far longer than a set: name it to run it)")
    p.add_argument("--samples", type=int, default=None, help="mismatch: samples per set (default 100)")
    p.add_argument("--refined-samples", type=int, default=None,
                   help="mismatch: samples of the sets solved again with quadratic elements ('quadratic elements' on "
                        f"the same mesh, 'discretisation' on the refined one; default {DISCRETISATION_SAMPLES})")
    p.add_argument("--refined-time-limit", type=float, default=None, metavar="SECONDS",
                   help="mismatch: wall-clock limit of one solve of those sets; a sample past it is "
                        "left out and recorded, and tried again only under a larger limit (default 900; 0 = none)")
    p.add_argument("--physics", type=int, default=0, metavar="N",
                   help="mismatch: also solve each set's first N frames through the physics inverse (the first model's "
                        "markers and training store's simulator, as `predict --physics`; seconds to minutes a frame), "
                        "a row 'physics' beside the models' (default 0: none)")
    p.add_argument("--physics-known-margin", action="store_true",
                   help="mismatch: the physics frames also with each one's simulated attached margin given, as "
                        "`predict --physics --attached-margin` a measured one (a row 'physics, margin known'; "
                        "needs --physics N and a training store that draws the margin)")
    p.add_argument("--physics-estimate", choices=("mean", "likeliest"),
                   help="mismatch: the physics rows' field where the attached margin is searched, as `predict "
                        "--physics-estimate` (default mean)")
    p.add_argument("--physics-time-limit", type=float, default=None, metavar="SECONDS",
                   help="mismatch: seconds one physics frame may take (default that of `predict --physics`; 0: none)")
    p.add_argument("--alpha", type=float, default=0.0,
                   help="mismatch: force magnitude of the sets, N (default: the first model's training store's)")
    p.set_defaults(func=run)


def _models(specs: list[str]) -> dict:
    """``{label: DeformationModel}`` from ``LABEL=DIR`` arguments."""
    from ..errors import ConfigError
    from ..surrogate import DeformationModel

    if not specs:
        raise ConfigError("study mismatch needs at least one --model LABEL=DIR (e.g. --model uncertain=runs/x/model)")
    out = {}
    for spec in specs:
        label, sep, folder = spec.partition("=")
        if not sep or not label or not folder:
            raise ConfigError(f"--model {spec!r}: give LABEL=DIR, e.g. nominal=runs/embedded/model")
        out[label] = DeformationModel.load(folder)
    return out


def _mismatch(args) -> int:
    from ..app.configuration import load_run_config
    from ..errors import ConfigError
    from ..evaluate import mismatch as mm
    from ..evaluate.mismatch_report import format_mismatch, mismatch_figure, write_mismatch
    from ..app.pipeline import run_paths

    if not args.source or Path(args.source).is_dir():
        raise ConfigError("study mismatch takes the scenario's TOML config or a packaged preset (e.g. embedded), not "
                          "a store: its sets are simulated from the config")
    limit = mm.REFINED_TIME_LIMIT if args.refined_time_limit is None else args.refined_time_limit
    if limit < 0:
        raise ConfigError(f"--refined-time-limit {limit:g}: give seconds > 0, or 0 for no limit")
    limit = limit or None
    if args.physics < 0:
        raise ConfigError(f"--physics {args.physics}: give a number of frames >= 0 (0: no physics rows)")
    from ..inverse import ESTIMATES
    from .predict_physics import TIME_LIMIT

    physics_limit = TIME_LIMIT if args.physics_time_limit is None else args.physics_time_limit
    if not physics_limit >= 0:
        raise ConfigError(f"--physics-time-limit {physics_limit:g}: give seconds > 0, or 0 for no limit")
    cfg = load_run_config(args.source)
    models = _models(args.model)
    first = next(iter(models.values()))
    alpha = args.alpha or (mm.store_alpha(first.dataset_path) if first.dataset_path else 0.0)
    if alpha <= 0:
        raise ConfigError("study mismatch: the first model records no training store with a calibrated alpha; "
                          "give --alpha (N)")
    out = Path(args.out) if args.out else run_paths(cfg).report
    samples = args.samples or mm.DEFAULT_SAMPLES
    refined = args.refined_samples or mm.DISCRETISATION_SAMPLES
    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    names = [s.name for s in mm.chosen_sets(cfg, first.mesh, sets)]
    print(f"mismatch study: {len(models)} model(s), sets {', '.join(names)}; {samples} samples a set ({refined} for "
          f"those solved again with quadratic elements), alpha {alpha:.4g} N; sets kept in {out / 'mismatch'} (a "
          "second run resumes them)" + (f"; the first {args.physics} frame(s) of each set also through the physics "
                                         "inverse" if args.physics else ""), flush=True)
    rows = mm.mismatch_study(cfg, models, out / "mismatch", alpha=alpha, sets=sets, samples=samples,
                             refined_samples=refined, refined_time_limit=limit, progress=True,
                             physics=mm.PhysicsRows(args.physics, physics_limit or None, args.physics_known_margin,
                                                    args.physics_estimate),
                             on_row=lambda r: print(f"  {r['set']} / {r['model']}: Offset_max {r['mlp_offset_max']:.3g} mm "
                                                    f"(rigid {r['rigid_offset_max']:.3g}), relative "
                                                    f"{100 * r['relative']:.3g} %", flush=True))
    markers = {k: m.describe()["markers"] for k, m in models.items()}
    meta = {"alpha": alpha, "samples": samples, "refined_samples": refined, "refined_time_limit": limit, "models": markers,
            "physics_frames": args.physics, "physics_known_margin": args.physics_known_margin,
            "physics_estimate": (args.physics_estimate or ESTIMATES[0]) if args.physics else None}
    json_path, csv_path = write_mismatch(out, rows, meta)
    png = mismatch_figure(rows, out / "study_mismatch.png")
    print(format_mismatch(rows))
    print(f"wrote {json_path}, {csv_path} and {png}")
    return 0


def run(args) -> int:
    if args.study == "mismatch":
        return _mismatch(args)
    from ..dataset import open_dataset
    from ..evaluate import figures, studies
    from ..app.pipeline import resolve_source, run_paths

    cfg, store = resolve_source(args.source, args.store)
    ds = open_dataset(store)
    out = Path(args.out) if args.out else run_paths(cfg, store).report
    out.mkdir(parents=True, exist_ok=True)

    def show(row):
        print("  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)

    if args.study == "architecture":
        rows = studies.architecture_study(ds, cfg, widths=_ints(args.widths), repeats=args.repeats, on_row=show)
        png = figures.architecture_grid(rows, out / "study_architecture.png")
    elif args.study == "markers":
        rows = studies.marker_count_study(ds, cfg, counts=_ints(args.counts), on_row=show)
        png = figures.marker_count_curve(rows, out / "study_markers.png")
    else:
        from ..surrogate import PCACurve
        import numpy as np

        rows = studies.pca_study(ds, cfg, max_components=args.max_components)
        chosen = next((r["n_components"] for r in rows if r["chosen"]), rows[-1]["n_components"])
        curve = PCACurve(np.array([r["n_components"] for r in rows]), np.array([r["max_error"] for r in rows]),
                         np.array([r["mean_max_error"] for r in rows]), np.array([r["mean_error"] for r in rows]),
                         chosen, cfg.surrogate.pca_max_error, cfg.surrogate.pca_folds)
        png = figures.pca_curve(curve, out / "study_pca.png")
        print(f"  chosen n_w = {chosen} (largest cross-validated vertex error < {cfg.surrogate.pca_max_error} mm)")
    csv_path = studies.write_rows(out / f"study_{args.study}.csv", rows)
    print(f"wrote {csv_path} and {png}")
    return 0
