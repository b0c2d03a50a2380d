"""Decoders side by side on a store: their floors, and the model's test-1 accuracy with each.

A decoder turns the coefficients the head and the networks predict into the field
(:mod:`tissuecast.surrogate.decoder`). For every decoder variant this prints

- its **floor** on test-1: the true fields projected on the decoder (the best any prediction
  decoded by it can do), fitted on the model's training samples (all of 'train'), with all its
  coefficients: mean Offset_max, mean Offset_mean, share of samples below 1 mm everywhere;
- for every marker count (k-center markers of the store's config, never on held vertices): the
  model's test-1 mean Offset_max, mean Offset_mean and share below 1 mm, its number of
  coefficients after the validation cut and the floor there, with rigid registration and the
  ridge baseline from the same markers beside it, and the fit time.

The models are fitted as ``tissuecast study markers`` fits them (the store's surrogate
settings, one network, no calibration hold-out). A variant is ``NAME[:key=value...]`` with
NAME ``pca`` or ``local`` (the ``surrogate.decoder`` values) and keys ``components`` (the
global PCA basis, ``surrogate.pca_max_components``), ``regions`` and ``local``
(``decoder_regions``, ``decoder_components``) and any ``[surrogate]`` training key (``epochs``,
``patience``, ``ensemble``).

``--tip`` adds the indentation's access vertex as one more marker (stores of a scenario with an
indentation): its displacement is the retractor's, what a tracked instrument tells the model.

Usage::

    python benchmarks/decoder_floor.py --dataset runs/embedded/dataset.zarr --markers 10 20 \\
        pca pca:components=512 local:components=128:regions=8:local=384
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.dataset.store import open_root
from tissuecast.evaluate.studies import study_markers
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.data import dataset_arrays, split_indices
from tissuecast.surrogate.decoder import fit_decoder

KEYS = {"components": "pca_max_components", "regions": "decoder_regions", "local": "decoder_components"}


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME[:key=value...]`` -> (label, surrogate overrides)."""
    name, *pairs = text.split(":")
    if name not in ("pca", "local"):
        raise SystemExit(f"unknown decoder {name!r}; use pca or local")
    opts = {"decoder": name}
    for pair in pairs:
        key, _, value = pair.partition("=")
        opts[KEYS.get(key, key)] = float(value) if "." in value else int(value)
    return text, opts


def errors(fields: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    """(mean Offset_max, mean Offset_mean, share of samples with Offset_max < 1 mm) in mm."""
    e = np.linalg.norm(fields - truth, axis=2)
    return float(e.max(axis=1).mean()), float(e.mean()), float(np.mean(e.max(axis=1) < 1.0))


def show(figures: tuple[float, float, float]) -> str:
    return f"{figures[0]:6.3f} {figures[1]:6.3f} {100 * figures[2]:4.0f} %"


def floors(arrays, bench: np.ndarray, variants, config) -> None:
    U = np.asarray(arrays.displacements[arrays.train_idx], dtype=np.float64).reshape(len(arrays.train_idx), -1)
    print(f"decoder floors on test-1 ({len(U)} training fields): mean Offset_max, mean Offset_mean (mm), "
          "share < 1 mm")
    for label, o in variants:
        sc = dataclasses.replace(config.surrogate, **{k: v for k, v in o.items() if k.startswith(("decoder", "pca"))})
        t0 = time.perf_counter()
        dec = fit_decoder(U, min(sc.pca_max_components, len(U) - 1), arrays.mesh, sc)
        proj = dec.inverse_transform(dec.transform(bench.reshape(len(bench), -1))).reshape(bench.shape)
        print(f"  {label:44s} {dec.n_components:4d} coefficients  {show(errors(proj, bench))}  "
              f"({time.perf_counter() - t0:.1f} s)", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("variants", nargs="*", default=["pca", "pca:components=512", "local:local=384"])
    p.add_argument("--markers", type=int, nargs="+", default=[10, 20])
    p.add_argument("--tip", action="store_true", help="the indentation access vertex as one more marker")
    p.add_argument("--no-models", action="store_true", help="floors only")
    args = p.parse_args()
    ds = open_dataset(args.dataset)
    arrays = dataset_arrays(ds)
    bench = np.asarray(ds.displacements[split_indices(ds, "test1")], dtype=np.float64)
    variants = [parse_variant(v) for v in args.variants]
    print(ds)
    floors(arrays, bench, variants, ds.config)
    if args.no_models:
        return
    tip = np.zeros(0, np.int64)
    if args.tip:
        root = open_root(args.dataset)
        if "scenario" not in root or "indent_access" not in root["scenario"]:
            raise SystemExit("--tip needs a store of a scenario with an indentation access region")
        tip = np.asarray(root["scenario/indent_access"][...], dtype=np.int64)[:1]
    ranked = study_markers(arrays.mesh, max(args.markers), ds.config, exclude=arrays.fixed)[0]
    print("test-1: mean Offset_max, mean Offset_mean (mm), share < 1 mm" + ("; markers + the instrument tip" if args.tip
                                                                             else "; markers only"))
    for n_d in args.markers:
        markers = np.r_[ranked[:n_d], tip]
        d = bench[:, markers, :]
        baselines = None
        for label, o in variants:
            t0 = time.perf_counter()
            m = DeformationModel(ds.config, **{"ensemble": 1, "calibration_share": 0.0, **o}).fit(
                arrays.displacements, markers, mesh=arrays.mesh, fixed=arrays.fixed, train_idx=arrays.train_idx,
                valid_idx=arrays.valid_idx)
            seconds = time.perf_counter() - t0
            floor = errors(m.pca_projection(bench), bench)
            print(f"  n_d {n_d:3d} {label:40s} n_w {m.n_components:4d} (floor {floor[0]:.3f})  "
                  f"model {show(errors(m.predict(d), bench))}  ({seconds:.0f} s)", flush=True)
            if baselines is None:
                baselines = [(meth, errors(m.predict(d, method=meth), bench)) for meth in ("rigid", "ridge")]
                for meth, fig in baselines:
                    print(f"  n_d {n_d:3d} {meth:40s} {'':20s}  {meth:5s} {show(fig)}")


if __name__ == "__main__":
    main()
