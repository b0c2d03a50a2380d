"""Split against cross-validated calibration of the error bounds and the alarm, on a data-set store.

For each calibration mode (``surrogate.calibration = "split" | "cross-validation"``) a model is
trained on the store with its own config (optionally fewer networks per fold model), then
measured on test-1: mean Offset_max (mm), the share of vertices within their 90 % / 95 %
bound, the median bound (mm), the alarm rate on clean inputs (target <= the configured 1 %),
on inputs with two markers' tracked positions swapped (every pair of markers, every sample)
and the input gate's verdict on one marker displaced by 1e9 mm and on a NaN marker. Prints one
table row per mode and the training-time ratio (cross-validation / split; only ratios mean
anything on a loaded machine).

    python benchmarks/calibration_modes.py --dataset runs/quick/dataset.zarr
    python benchmarks/calibration_modes.py --dataset STORE --fold-ensemble 1 --json out.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.errors import InputRejected
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.data import split_indices


def swapped_inputs(model, fields: np.ndarray) -> np.ndarray:
    """(B * P, n_d, 3) marker displacements (mm) with the tracked positions of one pair of markers
    swapped, for each of the P pairs and B fields (B, n, 3) mm."""
    ref = model.reference_marker_positions
    d = model.marker_displacements(fields)
    out = []
    for a, b in itertools.combinations(range(model.n_markers), 2):
        s = d.copy()
        s[:, a] = ref[b] + d[:, b] - ref[a]
        s[:, b] = ref[a] + d[:, a] - ref[b]
        out.append(s)
    return np.concatenate(out)


def caught(model, inputs: np.ndarray) -> float:
    """Share of inputs (B, n_d, 3) mm refused by the gate or alarmed by the trust layer."""
    refused = np.array([model.check_input(x).refused for x in inputs])
    alarmed = np.zeros(len(inputs), dtype=bool)
    keep = np.flatnonzero(~refused)
    if model.has_trust and len(keep):
        alarms = model.trusted_.predict_trusted(inputs[keep]).alarms
        alarmed[keep] = [a.raised for a in alarms]
    return float(np.mean(refused | alarmed))


def gate_verdict(model, d: np.ndarray) -> str:
    try:
        model.predict(d)
    except InputRejected as exc:
        return f"refused ({exc.reason})"
    return "predicted"


def measure(model, U: np.ndarray, test: np.ndarray) -> dict:
    """The row of one model on test-1 fields ``U[test]``."""
    fields = np.asarray(U[test], dtype=np.float64)
    d = model.marker_displacements(fields)
    row = {"offset_max_mm": float(np.linalg.norm(model.predict(d) - fields, axis=2).max(axis=1).mean())}
    if model.has_trust:
        for c in (0.9, 0.95):
            tp = model.predict_trusted(d, coverage=c)
            e = np.linalg.norm(tp.displacement - fields, axis=2)
            row[f"coverage_{c:g}"] = float(np.mean(e <= tp.error_bound))
            row[f"median_bound_{c:g}_mm"] = float(np.median(tp.error_bound))
        row["false_alarms"] = float(np.mean([a.raised for a in model.predict_trusted(d).alarms]))
    row["swapped_caught"] = caught(model, swapped_inputs(model, fields))
    glitch, nan = d[0].copy(), d[0].copy()
    glitch[0] += [1e9, 0.0, 0.0]
    nan[model.n_markers // 2] = np.nan
    row["glitch_1e9"] = gate_verdict(model, glitch)
    row["nan_marker"] = gate_verdict(model, nan)
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True, help="data-set store")
    p.add_argument("--modes", nargs="+", default=["split", "cross-validation"], choices=["split", "cross-validation"])
    p.add_argument("--fold-ensemble", type=int, default=0, help="networks per fold model (0: the model's ensemble)")
    p.add_argument("--folds", type=int, default=5, help="folds of the cross-validation")
    p.add_argument("--calibration-share", type=float, default=0.125,
                   help="split: share of the training split held out (default 0.125, the library default)")
    p.add_argument("--save", metavar="PREFIX", help="save each model to PREFIX-<mode>")
    p.add_argument("--json", help="write the rows to this file")
    args = p.parse_args(argv)
    ds = open_dataset(args.dataset)
    U = np.asarray(ds.displacements)
    test = split_indices(ds, "test1")
    rows = {}
    for mode in args.modes:
        t0 = time.perf_counter()
        model = DeformationModel.from_dataset(ds, calibration=mode, calibration_folds=args.folds,
                                              calibration_fold_ensemble=args.fold_ensemble,
                                              calibration_share=args.calibration_share)
        seconds = time.perf_counter() - t0
        if args.save:
            model.save(f"{args.save}-{mode}")
        rows[mode] = {"train_seconds": seconds, "n_train": model.training_["n_train"],
                      "n_calibration": model.training_["n_calibration"], **measure(model, U, test)}
        print(mode, json.dumps(rows[mode]), flush=True)
    if len(rows) == 2:
        ratio = rows["cross-validation"]["train_seconds"] / rows["split"]["train_seconds"]
        print(f"training time ratio cross-validation / split: {ratio:.2f}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"dataset": args.dataset, "test1": int(len(test)), "fold_ensemble": args.fold_ensemble, "rows": rows},
                      fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
