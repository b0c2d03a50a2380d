"""``tissuecast study {architecture,markers,pca} CONFIG|STORE``: the paper's parametric studies (CSV + PNG)."""

from __future__ import annotations

from pathlib import Path

from ..evaluate.studies import ARCHITECTURE_REPEATS, ARCHITECTURE_WIDTHS, MARKER_COUNTS, PCA_MAX_COMPONENTS

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


def register(sub) -> None:
    p = sub.add_parser("study", help="parametric studies: hidden layers, number of markers, PCA size",
                       description="Train on the store's train split and measure test-1 accuracy; writes study_NAME.csv "
                                   "and study_NAME.png into --out (default: the run's report folder), which "
                                   "`tissuecast evaluate` then includes in the report.")
    p.add_argument("study", choices=("architecture", "markers", "pca"), help="which study")
    p.add_argument("source", nargs="?", help="TOML config file or data-set store directory")
    p.add_argument("--store", help="store directory (default: dataset.store of the config)")
    p.add_argument("--out", help="output folder (default: the report folder of the config)")
    p.add_argument("--widths", default=_WIDTHS, help=f"architecture: layer widths (default {_WIDTHS})")
    p.add_argument("--repeats", type=int, default=ARCHITECTURE_REPEATS,
                   help=f"architecture: trainings per architecture (default {ARCHITECTURE_REPEATS})")
    p.add_argument("--counts", default=_COUNTS, help=f"markers: numbers of markers (default {_COUNTS})")
    p.add_argument("--max-components", type=int, default=PCA_MAX_COMPONENTS,
                   help=f"pca: largest n_w (default {PCA_MAX_COMPONENTS})")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..dataset import open_dataset
    from ..evaluate import figures, studies
    from ..evaluate.pipeline import resolve_source, run_paths

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
