"""What knowing a parameter is worth: models of an uncertain store fitted with each drawn
parameter given as an input (``scenario.uncertain.measured``), side by side.

A store simulated with ``[scenario.uncertain]`` draws the tissue's E, Poisson's ratio, the
surroundings' stiffness, the attached region's extent and the density anew for every sample;
a model that does not see them predicts, for given marker displacements, an average over the
hypotheses they leave open. Fitting the same model with some of them as inputs (what an
elastography measurement or a segmented attachment would give) and comparing the test errors
splits the model's error into what the markers cannot tell apart (removed by measuring the
parameter) and what the model itself leaves.

For every variant (a ``+``-joined list of parameter names, ``none`` or ``all``) this fits one
model on the store's 'train' split (the config's surrogate settings, its markers and
instruments, no trust layer) and prints, on the store's test-1 split and on every given
mismatch-study set (``tissuecast study mismatch`` keeps them under ``REPORT/mismatch/``; a set
with its parameters fixed records them, a nominal set records none and gets the nominal
values): the model's mean Offset_max, mean Offset_mean (mm) and rigid registration's mean
Offset_max from the same markers. ``--nominal STORE`` adds a model of the same settings fitted
on a store simulated without ``[scenario.uncertain]`` (the nominal-only model).

Usage::

    python benchmarks/information_floor.py configs/embedded.toml --dataset runs/embedded/dataset.zarr \\
        --nominal runs/nominal/dataset.zarr --sets runs/study/mismatch/nominal.zarr runs/study/mismatch/e_x2.zarr \\
        --variants none youngs_modulus spring_normal+spring_tangential attached_margin all
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from tissuecast.config import UNCERTAIN_PARAMETERS, load_config
from tissuecast.dataset import open_dataset
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.auxiliary import AuxiliaryInputs
from tissuecast.surrogate.data import dataset_auxiliary, split_indices

from decoder_floor import errors


def with_measured(config, names: tuple[str, ...]):
    """``config`` with ``scenario.uncertain.measured = names``."""
    unc = dataclasses.replace(config.scenario.uncertain, measured=names)
    return dataclasses.replace(config, scenario=dataclasses.replace(config.scenario, uncertain=unc))


def variant_names(text: str, config) -> tuple[str, ...]:
    """``none``, ``all`` (every parameter the config draws) or ``a+b+...`` -> parameter names."""
    if text == "none":
        return ()
    drawn = tuple(p for p in UNCERTAIN_PARAMETERS if p != "region_youngs_modulus" and getattr(config.scenario.uncertain, p))
    names = drawn if text == "all" else tuple(text.split("+"))
    bad = [n for n in names if n not in drawn]
    if bad:
        raise SystemExit(f"{bad} are not drawn by the config; it draws {list(drawn)}")
    return names


def set_inputs(model, ds, config) -> np.ndarray | None:
    """(N, n_a) the model's auxiliary inputs on a store: recorded poses and parameters, a
    parameter the store does not record (a set at the nominal values) or records as NaN
    (Poisson's ratio at its nominal value) taken at its nominal value."""
    aux = model.auxiliary
    if not aux.width:
        return None
    nominal = {"poisson_ratio": config.material.poisson_ratio, "attached_margin": 0.0}
    params = ds.parameters
    cols = [dataset_auxiliary(ds, AuxiliaryInputs(instruments=aux.instruments)).values]  # the recorded poses
    for name in aux.parameters:
        v = np.asarray(params[name], dtype=np.float64) if name in params else np.full(ds.n_samples, np.nan)
        cols.append(np.where(np.isnan(v), nominal.get(name, 1.0), v)[:, None])
    return np.hstack(cols)


def figures(model, ds, config, idx: np.ndarray) -> tuple[float, float, float]:
    """(model mean Offset_max, mean Offset_mean, rigid mean Offset_max) mm on samples ``idx``."""
    U = np.asarray(ds.displacements[idx], dtype=np.float64)
    d = U[:, model.markers, :]
    a = set_inputs(model, ds, config)
    with model.gate_suspended():  # perturbed sets may lie outside the training inputs: predict them all
        om, mean, _ = errors(model.predict(d, auxiliary=None if a is None else a[idx]), U)
        return om, mean, errors(model.predict(d, method="rigid"), U)[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="the uncertain store's config (its markers.ids and instruments are used)")
    p.add_argument("--dataset", required=True, help="a store simulated with [scenario.uncertain]")
    p.add_argument("--nominal", help="a store of the same scenario without [scenario.uncertain]")
    p.add_argument("--sets", nargs="*", default=[], help="mismatch-study sets (every sample is evaluated)")
    p.add_argument("--variants", nargs="+", default=["none", "all"])
    args = p.parse_args()
    config = load_config(args.config)
    ds = open_dataset(args.dataset)
    sets = [(Path(s).stem, open_dataset(s)) for s in args.sets]
    columns = [("test-1", ds, split_indices(ds, "test1"))] + [(n, s, s.select(status="done")) for n, s in sets]
    models = []
    if args.nominal:
        nom = open_dataset(args.nominal)
        models.append(("nominal-only", nom, config))
    models += [(f"measured: {v}", ds, with_measured(config, variant_names(v, config))) for v in args.variants]
    print(f"{ds}; columns: mean Offset_max / mean Offset_mean (mm), rigid's mean Offset_max beside")
    print(f"{'model':48s} " + " ".join(f"{n:>22s}" for n, _, _ in columns) + "   fit s")
    for label, store, cfg in models:
        t0 = time.perf_counter()
        model = DeformationModel.from_dataset(store, cfg, calibration="none")
        fit_s = time.perf_counter() - t0
        cells = []
        for _, s, idx in columns:
            om, mean, rigid = figures(model, s, cfg, idx)
            cells.append(f"{om:6.2f} / {mean:4.2f} ({rigid:5.2f})")
        print(f"{label:48s} " + " ".join(f"{c:>22s}" for c in cells) + f" {fit_s:7.0f}", flush=True)


if __name__ == "__main__":
    main()
