"""Robustness to the operating room: marker tracking noise, a missing marker, ensemble uncertainty.

Uses the DeformationModel hooks (``noise_sigma`` augmentation, ``marker_dropout`` masking
with ``predict(..., missing=...)``, ``ensemble`` with ``predict_with_uncertainty``) on a data
set written by ``tissuecast simulate`` and prints three tables (all lengths mm):

1. Noise: test-1 mean Offset_max when i.i.d. Gaussian noise of sigma = 0, 0.25, 0.5, 1.0 mm
   is added to every marker coordinate, for a network trained without augmentation, one
   trained with the same sigma (matched augmentation) and one trained with sigma = 0.5.
   Target: <= 1.0 mm at sigma = 0.5 mm. Each entry averages ``--draws`` noise draws.
2. Missing marker: test-1 mean Offset_max with each single marker untracked, for one masked
   network (trained with marker dropout) and for a
   :class:`~tissuecast.surrogate.robust.SubModelSet` (network i trained without marker i);
   the first row has every marker tracked.
3. Uncertainty: a ``--ensemble``-member ensemble (different seeds) gives per-vertex sigma;
   Spearman rank correlation of sigma with the true vertex error on test-1 and test-2,
   pooled over all vertices of all samples, and per sample (max sigma vs Offset_max).

Usage::

    python benchmarks/or_robustness.py --dataset dataset.zarr [--epochs 2000] [--json out.json]
    python benchmarks/or_robustness.py --synthetic      # plumbing check only: no FEM data
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from scipy.stats import spearmanr

from tissuecast.evaluate.metrics import offset_max
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.robust import SubModelSet

SIGMAS = (0.0, 0.25, 0.5, 1.0)


def load_dataset(path: str) -> dict:
    from tissuecast.dataset import open_dataset
    from tissuecast.surrogate.data import dataset_arrays, split_indices

    ds = open_dataset(path)
    arrays = dataset_arrays(ds)
    return {
        "name": f"FEM data set {path}", "config": ds.config, "U": np.asarray(arrays.displacements, dtype=np.float64),
        "markers": arrays.markers, "fixed": arrays.fixed, "mesh": arrays.mesh,
        "train": arrays.train_idx, "valid": arrays.valid_idx,
        "test1": split_indices(ds, "test1"), "test2": split_indices(ds, "test2"),
    }


def synthetic_dataset(n: int = 600, seed: int = 0) -> dict:
    """Smooth synthetic fields on the phantom; test-2 adds localised bumps (out of distribution)."""
    from tissuecast.markers import select_markers
    from tissuecast.mesh.phantom import phantom
    from tissuecast.serve.synthetic import synthetic_fields

    mesh = phantom()
    U = synthetic_fields(mesh, n + n // 10, peak=25.0, seed=seed)
    rng = np.random.default_rng(seed + 1)
    t2 = np.arange(n, len(U))
    for i in t2:  # a Gaussian bump of 3-8 mm around a random surface vertex
        centre = mesh.points[rng.choice(mesh.surface_vertices)]
        r2 = ((mesh.points - centre) ** 2).sum(axis=1)
        U[i] += rng.uniform(3, 8) * rng.normal(size=3) / np.sqrt(3) * np.exp(-r2 / (2 * 8.0**2))[:, None]
    order = rng.permutation(n)
    n_tr, n_va = int(0.8 * n), int(0.1 * n)
    return {
        "name": "SYNTHETIC smooth fields on the phantom (no FEM; plumbing check only)", "config": None, "U": U,
        "markers": select_markers(mesh), "fixed": np.zeros(0, np.int64), "mesh": mesh,
        "train": np.sort(order[:n_tr]), "valid": np.sort(order[n_tr:n_tr + n_va]),
        "test1": np.sort(order[n_tr + n_va:]), "test2": t2,
    }


class Study:
    def __init__(self, data: dict, epochs: int | None, seed: int):
        self.d, self.epochs, self.seed = data, epochs, seed
        self.rng = np.random.default_rng(seed)
        self.timings: dict[str, float] = {}
        self.n_components = 0

    def fit(self, label: str, markers=None, **overrides) -> DeformationModel:
        d = self.d
        if self.epochs:
            overrides.setdefault("epochs", self.epochs)
        if self.n_components:  # choose n_w (cross-validated, slow) once, then reuse it
            overrides.setdefault("n_components", self.n_components)
        t = time.perf_counter()
        model = DeformationModel(d["config"], **overrides).fit(
            d["U"], d["markers"] if markers is None else markers, mesh=d["mesh"], fixed=d["fixed"],
            train_idx=d["train"], valid_idx=d["valid"])
        self.timings[label] = time.perf_counter() - t
        self.n_components = self.n_components or model.n_components
        print(f"  fitted {label}: {model!r} in {self.timings[label]:.0f} s", flush=True)
        return model

    def markers_of(self, split: str, markers=None) -> tuple[np.ndarray, np.ndarray]:
        """(true fields (B, n, 3), marker displacements (B, n_d, 3)) of a split."""
        U = self.d["U"][self.d[split]]
        return U, U[:, self.d["markers"] if markers is None else markers, :]

    def noisy_error(self, model, sigma: float, draws: int) -> float:
        U, d = self.markers_of("test1")
        rng = np.random.default_rng(self.seed + int(sigma * 1000))
        values = [offset_max(model.predict(d + rng.normal(0.0, sigma, d.shape)), U).mean()
                  for _ in range(draws if sigma > 0 else 1)]
        return float(np.mean(values))

    # ------------------------------------------------------------------ the three studies
    def noise(self, draws: int) -> list[dict]:
        plain = self.fit("plain")
        fixed_aug = self.fit("noise_sigma=0.5", noise_sigma=0.5)
        rows = []
        for sigma in SIGMAS:
            matched = (plain if sigma == 0 else
                       fixed_aug if sigma == 0.5 else self.fit(f"noise_sigma={sigma}", noise_sigma=sigma))
            rows.append({"sigma": sigma, "no_augmentation": self.noisy_error(plain, sigma, draws),
                         "matched_augmentation": self.noisy_error(matched, sigma, draws),
                         "augmentation_0.5": self.noisy_error(fixed_aug, sigma, draws)})
        self.plain = plain
        return rows

    def missing(self, submodels: bool, dropout: float) -> list[dict]:
        masked = self.fit(f"marker_dropout={dropout}", marker_dropout=dropout)
        U, d = self.markers_of("test1")
        markers = np.asarray(self.d["markers"])
        subset = None
        if submodels:
            subs = [self.fit(f"without marker {i}", markers=np.delete(markers, i)) for i in range(len(markers))]
            subset = SubModelSet(self.plain, subs)
        rows = [{"missing": "none", "masked": float(offset_max(masked.predict(d), U).mean()),
                 "submodel": float(offset_max(self.plain.predict(d), U).mean())}]
        for i in range(len(markers)):
            row = {"missing": f"marker {i} (vertex {markers[i]})",
                   "masked": float(offset_max(masked.predict(d, missing=[i]), U).mean())}
            if subset is not None:
                row["submodel"] = float(offset_max(subset.predict(d, missing=[i]), U).mean())
            rows.append(row)
        return rows

    def uncertainty(self, members: int) -> list[dict]:
        ens = self.fit(f"ensemble={members}", ensemble=members)
        rows = []
        for split in ("test1", "test2"):
            if len(self.d[split]) < 3:
                rows.append({"set": split, "count": int(len(self.d[split]))})
                continue
            U, d = self.markers_of(split)
            u, sigma = ens.predict_with_uncertainty(d)
            err = np.linalg.norm(u - U, axis=-1)  # (B, n)
            single = offset_max(self.plain.predict(d), U)
            rows.append({
                "set": split, "count": int(len(U)),
                "spearman_vertices": float(spearmanr(sigma.ravel(), err.ravel()).statistic),
                "spearman_samples_max": float(spearmanr(sigma.max(axis=1), err.max(axis=1)).statistic),
                "mean_sigma": float(sigma.mean()),
                "ensemble_offset_max": float(err.max(axis=1).mean()), "single_offset_max": float(single.mean()),
            })
        return rows


def table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(title for _, title in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(f"{r[k]:.3f}" if isinstance(r.get(k), float) else str(r.get(k, "-")) for k, _ in columns)
            + " |" for r in rows]
    return "\n".join([head, rule, *body])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--dataset", help="data-set store written by `tissuecast simulate`")
    source.add_argument("--synthetic", action="store_true", help="synthetic fields (no FEM): plumbing check only")
    parser.add_argument("--epochs", type=int, help="override surrogate.epochs (default: the data set's config)")
    parser.add_argument("--ensemble", type=int, default=5)
    parser.add_argument("--draws", type=int, default=5, help="noise draws per sigma")
    parser.add_argument("--dropout", type=float, default=0.3, help="marker_dropout of the masked network")
    parser.add_argument("--no-submodels", action="store_true", help="skip the n_d sub-models")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write all figures to this JSON file")
    args = parser.parse_args()
    data = load_dataset(args.dataset) if args.dataset else synthetic_dataset(seed=args.seed)
    sizes = {k: int(len(data[k])) for k in ("train", "valid", "test1", "test2")}
    print(f"data: {data['name']}; {data['U'].shape[1]} vertices, markers {np.asarray(data['markers']).tolist()}, {sizes}")
    study = Study(data, args.epochs, args.seed)
    t0 = time.perf_counter()
    noise = study.noise(args.draws)
    missing = study.missing(not args.no_submodels, args.dropout)
    uncertainty = study.uncertainty(args.ensemble)
    print(f"\n## Marker noise: test-1 mean Offset_max (mm), {args.draws} draws per sigma\n")
    print(table(noise, [("sigma", "sigma (mm)"), ("no_augmentation", "no augmentation"),
                        ("matched_augmentation", "augmentation, same sigma"), ("augmentation_0.5", "augmentation 0.5 mm")]))
    print("\n## One marker missing: test-1 mean Offset_max (mm)\n")
    print(table(missing, [("missing", "untracked"), ("masked", f"masked network (dropout {args.dropout})"),
                          ("submodel", "sub-model without it (row 1: plain network)")]))
    print(f"\n## Ensemble uncertainty ({args.ensemble} networks): Spearman rank correlation with the true error\n")
    print(table(uncertainty, [("set", "set"), ("count", "samples"), ("spearman_vertices", "per vertex (pooled)"),
                              ("spearman_samples_max", "per sample (max sigma vs Offset_max)"), ("mean_sigma", "mean sigma"),
                              ("ensemble_offset_max", "ensemble Offset_max"), ("single_offset_max", "single-net Offset_max")]))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; training times (s): "
          + ", ".join(f"{k} {v:.0f}" for k, v in study.timings.items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"data": data["name"], "sizes": sizes, "noise": noise, "missing": missing,
                       "uncertainty": uncertainty, "training_seconds": study.timings}, f, indent=2)


if __name__ == "__main__":
    main()
