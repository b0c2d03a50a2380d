"""Training on the simulator's sensitivities, side by side with the paper's network.

For a store and either a model folder (its markers and run config: e.g. a model of the
embedded preset with planned markers) or a marker count (that many markers planned on the
store, ``tissuecast markers plan``'s rule, with the store's own config), fits each variant on
the store's training split and prints its test-1 mean Offset_max / mean Offset_mean / share of
samples below 1 mm everywhere (mm), the TRE at the model's targets (the phantom's 10 interior
points) with the share of their displacement corrected (mean over samples), the fit time, and
rigid registration and ridge from the same markers. The sensitivities
(``tissuecast.dataset.sensitivities``: du/dw at each training sample, one tangent
factorisation each) are computed once and timed; every variant that trains on them gets the
same array.

Variants are ``NAME[:key=value,...]`` of ``[surrogate]`` settings over the run config's
(values as TOML: ``hidden=[256,256]``). The defaults:

- ``paper``: the run config's settings as they are;
- ``wide``: two SiLU layers of 256, values only;
- ``sensitivities``: the same trained on the sensitivities (weight 30, 2 directions a sample
  a step, 1000 epochs: the embedded preset's settings).

Usage::

    python benchmarks/sensitivity_training.py --dataset STORE --model MODEL_FOLDER [--variants ...]
    python benchmarks/sensitivity_training.py --dataset STORE --markers 20 [--variants ...]
    python benchmarks/sensitivity_training.py --dataset BIG_STORE --markers 10 --sizes 800 1600 3200

``--sizes`` gives a learning curve: each variant trained on the first N samples of the training
split (the same validation and test-1 samples for every N; the fit time counts the N samples'
sensitivities at the measured cost per sample).
"""

from __future__ import annotations

import argparse
import time
import tomllib

import numpy as np

from tissuecast.app.pipeline import planned_config
from tissuecast.config import config_from_dict, with_overrides
from tissuecast.dataset import open_dataset
from tissuecast.dataset.sensitivities import dataset_sensitivities
from tissuecast.evaluate.evaluation import evaluate_model
from tissuecast.evaluate.metrics import share_corrected
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.auxiliary import AuxiliaryInputs
from tissuecast.surrogate.data import dataset_arrays

DEFAULT_VARIANTS = [
    "paper",
    'wide:hidden=[256,256],activation="silu"',
    'sensitivities:hidden=[256,256],activation="silu",sensitivity_weight=30.0,sensitivity_directions=2,epochs=1000',
]


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME[:key=value,...]`` -> (name, surrogate overrides); values are TOML."""
    name, _, rest = text.partition(":")
    over = tomllib.loads(f"v = {{{rest}}}")["v"] if rest else {}
    return name, over


def row(model, ds) -> dict:
    """Test-1 figures of ``model`` and its baselines on store ``ds``."""
    r = evaluate_model(model, ds, splits=("test1",)).sets["test1"]
    out = {}
    for meth in ("mlp", "rigid", "ridge"):
        o = r.offsets[meth]
        tre = r.tre[meth][:, 0]
        out[meth] = (o[:, 1].mean(), o[:, 0].mean(), (o[:, 1] < 1.0).mean(), tre.mean(),
                     np.nanmean(share_corrected(tre, r.target_displacement)))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    how = p.add_mutually_exclusive_group(required=True)
    how.add_argument("--model", help="a model folder: its markers and run config")
    how.add_argument("--markers", type=int, help="plan this many markers on the store (its own config)")
    p.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS)
    p.add_argument("--sizes", type=int, nargs="+", default=[],
                   help="train on the first N samples of the training split, for each N (a learning curve; default all)")
    a = p.parse_args()
    ds = open_dataset(a.dataset)
    if a.model:
        cfg = config_from_dict(DeformationModel.load(a.model).run_config)
    else:
        t0 = time.perf_counter()
        cfg, _ = planned_config(with_overrides(ds.config, markers={"count": a.markers, "ids": [], "rule": "planned"}), ds)
        print(f"{a.markers} markers planned in {time.perf_counter() - t0:.0f} s: {list(cfg.markers.ids)}", flush=True)
    markers = np.asarray(cfg.markers.ids, dtype=np.int64)
    arrays = dataset_arrays(ds, AuxiliaryInputs.from_config(cfg.scenario))
    variants = [parse_variant(v) for v in a.variants]
    train = np.asarray(arrays.train_idx)
    sizes = [n for n in a.sizes if n <= len(train)] or [len(train)]
    if len(sizes) < len(a.sizes):
        print(f"sizes above the {len(train)} training samples skipped", flush=True)
    sens, t_sens = None, 0.0
    if any(o.get("sensitivity_weight", 0) > 0 for _, o in variants):
        t0 = time.perf_counter()
        sens = dataset_sensitivities(ds, train[:max(sizes)])
        t_sens = (time.perf_counter() - t0) / max(sizes)  # per sample
        print(f"sensitivities of {max(sizes)} training samples: {t_sens * max(sizes):.0f} s", flush=True)
    print(f"{'variant':14s} {'N':>5s} {'fit s':>6s}  {'Offset_max':>10s} {'mean':>6s} {'<1mm':>5s}  {'TRE':>6s} {'corr.':>6s}   "
          f"rigid (max / TRE / corr.)   ridge", flush=True)
    for n in sizes:
        for name, over in variants:
            c = with_overrides(cfg, surrogate=over)
            t0 = time.perf_counter()
            model = DeformationModel(c)
            model.scenario = ds.scenario
            model.fit(arrays.displacements, markers, mesh=arrays.mesh, fixed=arrays.fixed, train_idx=train[:n],
                      valid_idx=arrays.valid_idx, auxiliary=arrays.auxiliary,
                      sensitivities=sens if c.surrogate.sensitivity_weight > 0 else None)
            fit = time.perf_counter() - t0 + (t_sens * n if c.surrogate.sensitivity_weight > 0 else 0.0)
            r = row(model, ds)
            m, g, q = r["mlp"], r["rigid"], r["ridge"]
            print(f"{name:14s} {n:5d} {fit:6.0f}  {m[0]:10.3f} {m[1]:6.3f} {100 * m[2]:4.0f}%  {m[3]:6.3f} {100 * m[4]:5.1f}%   "
                  f"{g[0]:.2f} / {g[3]:.2f} / {100 * g[4]:.1f}%   {q[0]:.2f} / {q[3]:.2f} / {100 * q[4]:.1f}%", flush=True)


if __name__ == "__main__":
    main()
