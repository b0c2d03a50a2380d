"""Corrections at prediction time, measured: what the simulator's sensitivities and the tracked
instrument's neighbourhood could add to a trained model.

For a store and a model folder trained on it (linear elements: the sensitivities need them),
predicts test-1 from the model's markers (and tracked instruments) and prints mean Offset_max /
mean Offset_mean / share of samples below 1 mm everywhere (mm) of:

- the model as it is, and its error at the markers themselves (how closely it already fits them);
- the model corrected in the span of the simulator's sensitivities: its marker residual
  (tracked minus predicted at the markers) fitted, by ridge, with the sensitivities
  (:func:`tissuecast.dataset.sensitivities.dataset_sensitivities`, du per prior standard
  deviation of each load weight and drawn parameter) of the ``--neighbours`` training samples
  nearest in marker displacement, or with the ``--global-directions`` leading singular vectors
  of all training samples' sensitivities; the fitted combination added to the whole field;
- the nearest training sample moved to the tracked markers along its own sensitivities (one
  linear step from the simulation nearest in marker space);
- for a store with a tracked instrument: the model's figures with and without contact, the
  distance of the worst vertex from the tip, and the model's figures were its field exact within
  ``--radii`` mm of the tip (the most any decoder resolving the instrument's dent could give).

The ridge weights ``--ridge`` penalise the squared coefficients (in prior standard deviations)
against the squared marker misfit: mm^2 per squared standard deviation. Usage::

    python benchmarks/prediction_corrections.py --dataset STORE --model MODEL_FOLDER
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.dataset.sensitivities import dataset_sensitivities
from tissuecast.evaluate.evaluation import auxiliary_values
from tissuecast.evaluate.metrics import vertex_errors
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.data import split_indices


def figures(error: np.ndarray) -> str:
    """``mean Offset_max / mean Offset_mean / share below 1 mm`` of per-vertex errors (N, n) mm."""
    worst = error.max(axis=1)
    return f"{worst.mean():.3f} / {error.mean():.3f} / {100 * (worst < 1.0).mean():.0f} %"


def ridge_fit(J: np.ndarray, r: np.ndarray, lam: float) -> np.ndarray:
    """(k,) coefficients minimising |J.T c - r|^2 + lam |c|^2 for directions J (k, m), residual r (m,)."""
    return np.linalg.solve(J @ J.T + lam * np.eye(len(J)), J @ r)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--model", required=True)
    p.add_argument("--neighbours", type=int, nargs="+", default=[1, 3])
    p.add_argument("--global-directions", type=int, nargs="+", default=[10, 30, 60])
    p.add_argument("--ridge", type=float, nargs="+", default=[1e-3, 1e-1])
    p.add_argument("--radii", type=float, nargs="+", default=[8.0, 12.0, 20.0])
    a = p.parse_args()
    ds = open_dataset(a.dataset)
    model = DeformationModel.load(a.model)
    mk = np.asarray(model.markers)
    train, test = np.sort(split_indices(ds, "train")), split_indices(ds, "test1")
    U = np.asarray(ds.displacements, dtype=np.float64)
    truth, sims = U[test], U[train]
    aux = auxiliary_values(model, ds)
    pred = model.predict(truth[:, mk], auxiliary=None if aux is None else aux[test])
    e = vertex_errors(pred, truth)
    print(f"test-1: {len(test)} samples; the model {figures(e)}; its error at the markers {e[:, mk].mean():.3f} mm "
          f"on average, {e[:, mk].max(axis=1).mean():.3f} at the worst marker", flush=True)

    t0 = time.perf_counter()
    S = dataset_sensitivities(ds, train).values  # (M, k, n, 3)
    print(f"sensitivities of {len(train)} training samples along {S.shape[1]} directions: "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    usable = np.isfinite(S).all(axis=(2, 3))  # (M, k)
    observed = truth[:, mk].reshape(len(test), -1)
    at_markers = sims[:, mk].reshape(len(train), -1)
    residual = observed - pred[:, mk].reshape(len(test), -1)
    order = np.argsort(np.linalg.norm(at_markers[None] - observed[:, None], axis=2), axis=1)  # (N, M)
    for lam in a.ridge:
        for K in a.neighbours:
            out = pred.copy()
            for i in range(len(test)):
                J = np.concatenate([S[k][usable[k]] for k in order[i, :K]])
                out[i] += np.tensordot(ridge_fit(J[:, mk].reshape(len(J), -1), residual[i], lam), J, 1)
            print(f"ridge {lam:g}, the {K} nearest samples' sensitivities: {figures(vertex_errors(out, truth))}",
                  flush=True)
        moved = np.empty_like(truth)
        for i in range(len(test)):
            k = order[i, 0]
            J = S[k][usable[k]]
            c = ridge_fit(J[:, mk].reshape(len(J), -1), observed[i] - at_markers[k], lam)
            moved[i] = sims[k] + np.tensordot(c, J, 1)
        print(f"ridge {lam:g}, the nearest sample moved along its sensitivities: "
              f"{figures(vertex_errors(moved, truth))}", flush=True)
    flat = S[usable]  # (M k', n, 3)
    rng = np.random.default_rng(0)
    flat = flat[rng.choice(len(flat), min(len(flat), 8000), replace=False)].reshape(-1, S.shape[2] * 3)
    _, _, Vt = np.linalg.svd(flat, full_matrices=False)
    for q in a.global_directions:
        B = Vt[:q].reshape(q, -1, 3)
        PB = B[:, mk].reshape(q, -1)
        for lam in a.ridge:
            c = np.linalg.solve(PB @ PB.T + lam * np.eye(q), PB @ residual.T).T
            out = pred + np.tensordot(c, B, 1)
            print(f"ridge {lam:g}, {q} global sensitivity directions: {figures(vertex_errors(out, truth))}",
                  flush=True)

    points = np.asarray(ds.mesh.points, dtype=np.float64)
    for name, pose in ds.instrument_poses.items():
        contact = np.asarray(pose["contact"])[test] == 1
        tip = np.asarray(pose["tip"], dtype=np.float64)[test]
        print(f"instrument {name!r}: in contact {contact.sum()} samples {figures(e[contact])}, away {(~contact).sum()} "
              f"{figures(e[~contact])}")
        if contact.any():
            d = np.linalg.norm(points[e.argmax(axis=1)] - tip, axis=1)[contact]
            print("  worst vertex's distance from the tip in contact, percentiles 25/50/75: "
                  + " / ".join(f"{v:.1f}" for v in np.percentile(d, [25, 50, 75])) + " mm")
            dist = np.linalg.norm(points[None] - tip[:, None], axis=2)  # (N, n)
            for r in a.radii:
                exact = (dist < r) & contact[:, None]
                print(f"  field exact within {r:g} mm of the tip: {figures(np.where(exact, 0.0, e))}")


if __name__ == "__main__":
    main()
