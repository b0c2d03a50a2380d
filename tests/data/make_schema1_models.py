"""Write the model folders of ``tests/data/schema1_models/`` and their expected outputs.

Run once at commit 43d0509 (before the model was composed of its parts), with that commit's
``src`` first on ``PYTHONPATH``:  ``python tests/data/make_schema1_models.py``.
``tests/surrogate/test_surrogate_compat.py`` loads the folders with today's code and checks that every
output is what the code that wrote them gave. Uses only the public API, so it also runs today.
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent))

from _surrogate_synthetic import box_mesh, nonlinear_fields  # noqa: E402

from tissuecast.surrogate import DeformationModel  # noqa: E402

MARKERS = np.array([0, 8, 17, 26, 35])
KINDS = {
    # the default: quadratic head under a 2-network ensemble, calibrated bounds and alarm
    "head_trust": dict(hidden=(16, 8), ensemble=2, pca_max_components=10),  # 100 training samples
    # the paper's network alone, fault score in the alarm (the trust layer fits its own second predictor)
    # (30 training samples: the second predictor's basis has at most as many components, the folder stays small)
    "nohead_fault": dict(hidden=(16, 8), head="none", n_components=8, alarm_fault_score=True),
    # marker dropout: predicts with untracked markers; no calibration
    "masked": dict(hidden=(16, 8), marker_dropout=0.3, n_components=8, ensemble=2, calibration_share=0.0),
}


def data():
    mesh = box_mesh(2, 2, 3)  # 36 vertices
    theta = np.random.default_rng(5).uniform(-1, 1, (320, 3))
    return mesh, nonlinear_fields(mesh, theta)


def inputs(mesh, U):
    """Marker displacements (8, 5, 3) mm: 4 held-out fields, 2 with one marker 3 mm off, 2 far outside."""
    d = U[300:308][:, MARKERS, :].copy()
    d[4:6, 1] += 3.0
    d[6:8] *= 3.0
    return d


def outputs(model, d) -> dict:
    """Every prediction of ``model`` for inputs ``d`` (B, 5, 3) mm, as arrays."""
    out = {"mlp": model.predict(d), "ridge": model.predict(d, method="ridge"), "rigid": model.predict(d, method="rigid")}
    if model.supports_missing_markers:
        out["mlp_missing"] = model.predict(d, missing=[2])
    if model.ensemble_size > 1:
        out["uncertainty"] = model.predict_with_uncertainty(d)[1]
    if model.has_trust:  # the defaults (an infinite alarm threshold with 60 calibration samples) and 80 % / 10 %
        for key, kw in (("", {}), ("_loose", {"coverage": 0.8, "false_alarm": 0.1})):
            tp = model.predict_trusted(d, **kw)
            out[f"bound{key}"] = tp.error_bound
            out[f"alarm{key}"] = np.array([[a.raised, a.distance, a.consistency, a.fault, a.marker, a.distance_threshold,
                                            a.consistency_threshold, a.fault_threshold] for a in tp.alarms])
    return out


def main():
    mesh, U = data()
    for name, kw in KINDS.items():
        n_train = 30 if name == "nohead_fault" else 100
        m = DeformationModel(epochs=30, patience=0, batch_size=32, **kw).fit(
            U[:300], MARKERS, mesh=mesh, fixed=[1, 2], train_idx=np.arange(n_train), valid_idx=np.arange(200, 240),
            calibration_idx=None if kw.get("calibration_share") == 0.0 else np.arange(240, 300))
        folder = HERE / "schema1_models" / name
        m.save(folder)  # the expected outputs are the saved folder's (bounds from float32-stored scores)
        np.savez_compressed(folder / "expected_outputs.npz", **outputs(DeformationModel.load(folder), inputs(mesh, U)))


if __name__ == "__main__":
    main()
