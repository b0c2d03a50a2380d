"""Where a model's error sits on a store whose scenario draws the attached margin.

For a store (e.g. the embedded preset as shipped, parameters drawn) and a model folder trained
on it, predicts test-1 from the model's markers (and tracked instruments) and prints:

- per quarter of the margin's range: the samples, mean Offset_max, mean vertex error, and the
  share whose worst vertex lies within ``--near`` mm of the rim band;
- the rim band: the surface vertices within the margin range's reach of the nominal attached
  face's edge (those a drawn margin can hold or free), their mean error against the others';
- the mean Offset_max were the band's vertices exact.

Usage::

    python benchmarks/error_location.py --dataset STORE --model MODEL_FOLDER [--near 3]
"""

from __future__ import annotations

import argparse

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.dataset.worker import SampleContext
from tissuecast.evaluate.evaluation import auxiliary_values
from tissuecast.evaluate.metrics import vertex_errors
from tissuecast.surrogate import DeformationModel


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--model", required=True)
    p.add_argument("--near", type=float, default=3.0, help="mm from the rim band that counts as at the rim")
    a = p.parse_args()
    ds = open_dataset(a.dataset)
    model = DeformationModel.load(a.model)
    uncertain = SampleContext(ds.recipe()).scenario.uncertain
    if uncertain is None or uncertain.distance is None or "attached_margin" not in ds.parameters:
        raise SystemExit(f"{a.dataset}: its scenario does not draw the attached margin")
    lo, hi = (float(v) for v in ds.config.scenario.uncertain.attached_margin)
    reach = max(abs(lo), abs(hi))
    band = np.isfinite(uncertain.distance) & (np.abs(uncertain.distance) <= reach)
    idx = ds.select("test1")
    truth = np.asarray(ds.displacements[idx], dtype=np.float64)
    aux = auxiliary_values(model, ds)
    e = vertex_errors(model.predict(truth[:, model.markers, :], auxiliary=None if aux is None else aux[idx]), truth)  # (N, n) mm
    points = np.asarray(ds.mesh.points, dtype=np.float64)
    worst = points[e.argmax(axis=1)]
    to_band = np.min(np.linalg.norm(worst[:, None, :] - points[band][None, :, :], axis=2), axis=1)
    near = to_band <= a.near
    margin = np.asarray(ds.parameters["attached_margin"])[idx]
    print(f"test-1: {len(idx)} samples, mean Offset_max {e.max(axis=1).mean():.2f} mm, mean vertex error {e.mean():.3f} mm; "
          f"worst vertex within {a.near:g} mm of the rim band on {100 * near.mean():.0f} %")
    print(f"{'margin (mm)':>16s} {'samples':>8s} {'Offset_max':>11s} {'mean':>7s} {'at the rim':>11s}")
    edges = np.linspace(lo, hi, 5)
    for k, (a0, a1) in enumerate(zip(edges[:-1], edges[1:])):
        s = (margin >= a0) & ((margin < a1) if k < 3 else (margin <= a1))
        if s.any():
            print(f"{a0:7.2f} to {a1:5.2f} {s.sum():8d} {e.max(axis=1)[s].mean():11.2f} {e[s].mean():7.3f} "
                  f"{100 * near[s].mean():10.0f} %")
    print(f"rim band: {band.sum()} vertices, mean error {e[:, band].mean():.3f} mm against {e[:, ~band].mean():.3f} elsewhere; "
          f"mean Offset_max were they exact {np.where(band, 0.0, e).max(axis=1).mean():.2f} mm")


if __name__ == "__main__":
    main()
