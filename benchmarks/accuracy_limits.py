"""What limits a store's surrogate accuracy: training, data size, information, or the basis.

Trains one regressor per variant on the store's 'train' split (PCA of the training fields with
``--components`` components; 'valid' checkpoints the networks) and prints its test-1 mean
Offset_max and mean Offset_mean (mm). A variant is ``KIND[:key=value...]``:

- ``network``: the paper's MLP (the store's surrogate settings) from k-center marker
  displacements; keys ``markers`` (count, default ``--markers``), ``tip=1`` (the retractor's
  access vertex as one more marker, for scenario stores with an indentation), ``ntrain`` (first
  N training samples), and any ``[surrogate]`` training key (``epochs``, ``patience``,
  ``learning_rate``, ``weight_decay``, ``hidden=256-256``).
- ``quadratic``: ridge regression on linear and quadratic features (the quadratic head alone,
  :mod:`tissuecast.surrogate.head`); keys ``markers``, ``tip``, ``ntrain``, ``q`` (directions).
- ``head``: the quadratic head with the network trained on its residual; keys as ``network``
  plus ``q``.
- ``oracle``: the network from the sample's true load parameters instead of markers (LBO
  weights, and for scenario stores the gravity direction and the indentation's displacement,
  depth and slide): what an input that knows the load exactly would give.

``--where`` prints where the largest errors of the first network variant sit: distance of each
test sample's worst vertex to the indentation access point and to the held vertices, and the
vertices with the largest mean error.

Usage::

    python benchmarks/accuracy_limits.py --dataset runs/embedded/dataset.zarr \\
        network oracle network:ntrain=400 network:markers=80 quadratic:q=24 head:q=24 network:tip=1 --where
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.dataset.store import open_root
from tissuecast.evaluate.studies import study_markers
from tissuecast.surrogate.data import split_indices
from tissuecast.surrogate.mlp import train_mlp
from tissuecast.surrogate.pca import fit_pca
from tissuecast.surrogate.quadratic import fit_quadratic

INT_KEYS = ("markers", "ntrain", "tip", "q", "epochs", "patience")


def parse_variant(text: str) -> tuple[str, dict]:
    kind, *pairs = text.split(":")
    if kind not in ("network", "quadratic", "head", "oracle"):
        raise SystemExit(f"unknown variant kind {kind!r}; use network, quadratic, head or oracle")
    opts = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key == "hidden":
            opts[key] = tuple(int(v) for v in value.split("-"))
        elif key in INT_KEYS:
            opts[key] = int(value)
        else:
            opts[key] = float(value)
    return kind, opts


def load_parameters(path, n: int) -> np.ndarray:
    """(n, 3 m) the samples' true load parameters, padded to a multiple of 3 columns."""
    s = open_root(path)["samples"]
    cols = [np.asarray(s["weights"][...]).reshape(n, -1)]
    for name in ("gravity_direction", "indent_displacement", "indent_depth", "indent_slide"):
        if name in s:
            cols.append(np.asarray(s[name][...], dtype=np.float64).reshape(n, -1))
    P = np.hstack(cols)
    return np.hstack([P, P[:, : (-P.shape[1]) % 3]])  # train_mlp takes inputs in 3-vectors


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("variants", nargs="+")
    p.add_argument("--components", type=int, default=128)
    p.add_argument("--markers", type=int, default=20)
    p.add_argument("--where", action="store_true")
    args = p.parse_args()
    ds = open_dataset(args.dataset)
    U = np.asarray(ds.displacements, dtype=np.float64)
    tr, va, te = (split_indices(ds, s) for s in ("train", "valid", "test1"))
    basis = fit_pca(U[tr].reshape(len(tr), -1), min(args.components, len(tr) - 1))
    Yt, Yv = basis.transform(U[tr].reshape(len(tr), -1)), basis.transform(U[va].reshape(len(va), -1))
    floor = np.linalg.norm(basis.inverse_transform(basis.transform(U[te].reshape(len(te), -1))).reshape(U[te].shape) - U[te],
                           axis=2).max(axis=1).mean()
    print(f"{ds}\nPCA: {basis.n_components} components, test-1 floor {floor:.3f} mm; {len(tr)} training samples")
    fixed = np.asarray(ds.fixed, dtype=np.int64)
    root = open_root(args.dataset)
    has_access = "scenario" in root and "indent_access" in root["scenario"]
    access = np.asarray(root["scenario/indent_access"][...]) if has_access else None
    cfg = ds.config.surrogate
    first_errors = None
    for text in args.variants:
        kind, o = parse_variant(text)
        t0 = time.perf_counter()
        if kind == "oracle":
            X = load_parameters(args.dataset, len(U))
        else:
            mk = study_markers(ds.mesh, o.pop("markers", args.markers), ds.config, exclude=fixed)[0]
            if o.pop("tip", 0):
                if access is None:
                    raise SystemExit("tip=1 needs a store with an indentation access region")
                mk = np.r_[mk, access[:1]]
            X = U[:, mk, :].reshape(len(U), -1)
        n = o.pop("ntrain", len(tr))
        q = o.pop("q", 12)
        Xt, Yt_n = X[tr][:n], Yt[:n]
        W = np.zeros((len(te), basis.n_components))
        if kind in ("quadratic", "head"):
            reg = fit_quadratic(Xt, Yt_n, quadratic_dims=q)
            W += reg.predict(X[te])
        if kind in ("network", "head", "oracle"):
            c = dataclasses.replace(cfg, **o)
            if kind == "head":
                w, _ = train_mlp(Xt, Yt_n - reg.predict(Xt), X[va], Yv - reg.predict(X[va]), c)
            else:
                w, _ = train_mlp(Xt, Yt_n, X[va], Yv, c)
            W += w.predict_weights(X[te])
        e = np.linalg.norm(basis.inverse_transform(W).reshape(U[te].shape) - U[te], axis=2)
        print(f"{text:40s} inputs {X.shape[1]:4d}  test-1 mean Offset_max {e.max(axis=1).mean():.3f} mm, "
              f"mean Offset_mean {e.mean():.3f} mm  ({time.perf_counter() - t0:.0f} s)", flush=True)
        if first_errors is None and kind == "network":
            first_errors = e
    if args.where and first_errors is not None:
        where(first_errors, ds.mesh.points, fixed, access)


def where(e: np.ndarray, points: np.ndarray, fixed: np.ndarray, access) -> None:
    worst = e.argmax(axis=1)
    to_fixed = np.linalg.norm(points[:, None] - points[fixed][None], axis=2).min(axis=1) if fixed.size else None
    to_access = np.linalg.norm(points - points[access[0]], axis=1) if access is not None else None
    print("worst vertex of each test-1 sample (first network variant), percentiles 10/50/90:")
    if to_access is not None:
        print(f"  distance to the indentation access point: {np.percentile(to_access[worst], [10, 50, 90]).round(1)} mm")
    if to_fixed is not None:
        print(f"  distance to the nearest held vertex: {np.percentile(to_fixed[worst], [10, 50, 90]).round(1)} mm")
    top = np.argsort(-e.mean(axis=0))[:10]
    print("vertices with the largest mean error (id, mean error mm, to access mm, to held mm):")
    for v in top:
        print(f"  {v:5d} {e[:, v].mean():6.2f} {'' if to_access is None else f'{to_access[v]:6.1f}'} "
              f"{'' if to_fixed is None else f'{to_fixed[v]:6.1f}'}")


if __name__ == "__main__":
    main()
