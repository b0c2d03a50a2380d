"""``tissuecast train CONFIG|STORE``: fit the PCA + MLP surrogate (and ridge baseline) on a data set."""

from __future__ import annotations

from pathlib import Path

from ..evaluate import json_output
from .help_examples import with_examples


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast train quick",
     "the model of the preset's store, into the config's output folder"),
    ("tissuecast train runs/quick/dataset.zarr --ensemble 3 --out model3",
     "from a store alone, three networks (uncertainty)"),
)


def register(sub) -> None:
    p = sub.add_parser("train", help="train the surrogate model on a data set",
                       description="Fit PCA (n_w by surrogate.pca_rule, the validation rule by default, unless "
                                   "surrogate.n_components is set), the ridge baseline and the MLP on the store's "
                                   "train split (valid split for checkpointing), "
                                   "and save the model folder (weights, PCA basis, mesh, metadata, ONNX).",
                       **with_examples(*EXAMPLES))
    p.add_argument("source", nargs="?",
                   help="TOML config file, a packaged preset or a data-set store directory (default: defaults)")
    p.add_argument("--store", help="store directory (default: dataset.store of the config)")
    p.add_argument("--out", help="model folder (default: model/ in the config's output folder)")
    p.add_argument("--hidden", type=int, nargs="+", help="hidden layer widths (default: surrogate.hidden)")
    p.add_argument("--components", type=int, help="PCA components n_w (default: surrogate.n_components; 0 = rule)")
    p.add_argument("--epochs", type=int, help="maximum epochs")
    p.add_argument("--ensemble", type=int, help="networks in the ensemble (>= 2 gives uncertainty)")
    p.add_argument("--noise", type=float, help="marker noise augmentation sigma (mm)")
    p.add_argument("--marker-dropout", type=float, help="share of samples with one marker hidden (enables missing markers)")
    p.add_argument("--seed", type=int, help="training seed")
    p.add_argument("--no-onnx", action="store_true", help="do not write model.onnx")
    p.add_argument("--json", action="store_true", help="print the training summary as JSON")
    p.set_defaults(func=run)


def overrides_from_args(args) -> dict:
    o = {}
    for name, key in (("hidden", "hidden"), ("components", "n_components"), ("epochs", "epochs"), ("ensemble", "ensemble"),
                      ("noise", "noise_sigma"), ("marker_dropout", "marker_dropout"), ("seed", "seed")):
        v = getattr(args, name, None)
        if v is not None:
            o[key] = v
    return o


def run(args) -> int:
    from ..config import with_overrides
    from ..app.pipeline import resolve_source, run_paths, train_from_store

    cfg, store = resolve_source(args.source, args.store)
    o = overrides_from_args(args)
    if o:
        cfg = with_overrides(cfg, surrogate=o)
    out = Path(args.out) if args.out else run_paths(cfg, store).model
    model, _ = train_from_store(cfg, store, model_folder=out, onnx=not args.no_onnx)
    tr = model.training_
    if args.json:
        print(json_output.dumps({"model": str(out), **tr}, indent=2))
        return 0
    print(f"model saved to {out}")
    print(f"  {model!r}")
    cal = tr.get("calibration") or {}
    how = {"cross-validation": f"out-of-fold, {cal.get('folds')} folds, ", "split": "held out, "}.get(cal.get("method"), "")
    print(f"  training samples {tr['n_train']}, validation {tr['n_valid']}, calibration {tr.get('n_calibration', 0)} "
          f"({how}error bounds and alarm{'' if model.has_trust else ': none'}), PCA components n_w = {tr['n_components']} "
          f"(rule: {tr.get('pca_rule', '?')})")
    q = ((model.pca_choice_ or {}).get("head") or {}).get("dims")
    if q is not None:
        print(f"  quadratic head under the network: products of q = {q} input directions (docs/surrogate.md)")
    vc = (model.pca_choice_ or {}).get("validation_curve")
    if vc:
        k = tr["n_components"] - 1
        print(f"  validation mean Offset_max at n_w = {k + 1}: model {vc['model_offset_max'][k]:.3f} mm, "
              f"PCA floor {vc['floor_offset_max'][k]:.3f} mm")
    for k, m in enumerate(tr["members"]):
        print(f"  member {k}: {m['epochs_run']} epochs (best {m['best_epoch']}), {m['seconds']:.1f} s, "
              f"best validation loss {m['best_valid_loss']:.3g}")
    if model.auxiliary.width:
        print(f"  auxiliary inputs: {', '.join(f'{n} [{u}]' for n, u in zip(model.auxiliary.names, model.auxiliary.units))}")
    if "fallback" in tr:
        fb = tr["fallback"]
        print(f"  fallback without the instruments (tracking lost): n_w = {fb['n_components']}, MLP {fb['mlp_seconds']:.1f} s")
    print(f"  total {tr['seconds']:.1f} s (PCA rule {tr['pca_seconds']:.1f} s, MLP {tr['mlp_seconds']:.1f} s)")
    return 0
