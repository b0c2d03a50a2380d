"""Model folders written before the model was composed of its parts still load, and predict what
the code that wrote them predicted.

``tests/data/schema1_models/`` holds three tiny folders written at commit 43d0509 by
``tests/data/make_schema1_models.py`` (a quadratic head under an ensemble with bounds and alarm;
the network alone with the fault score in the alarm; marker dropout without calibration), each
with ``expected_outputs.npz``: that commit's predictions for fixed inputs. On the machine that
wrote them the outputs match bit for bit; the tolerance here allows for another BLAS and, where
the compiled predictor takes part, for its float32 products (it multiplied in float64 when the
folders were written): fields to float32's rounding, spreads and bounds to a relative 1e-5, and
the bounds of ``head_trust`` to a relative 0.1: its networks correct the head by almost nothing,
so the error model's inputs (the log of the field's miss at the markers, of the disagreement)
are of the size of float32's rounding of the fields there.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tissuecast.surrogate import DeformationModel

DATA = Path(__file__).resolve().parents[1] / "data"
sys.path.insert(0, str(DATA))

from make_schema1_models import KINDS, data, inputs, outputs  # noqa: E402
from _surrogate_synthetic import COMPILED_ATOL  # noqa: E402

RTOL, ATOL = 1e-9, 1e-12
#: (rtol, atol mm) of the outputs the compiled predictor computes, by kind (module docstring).
COMPILED = {"mlp": (0.0, COMPILED_ATOL), "mlp_missing": (0.0, COMPILED_ATOL), "uncertainty": (1e-5, 0.0),
            "bound": (1e-5, 0.0), "bound_loose": (1e-5, 0.0)}
NEAR_EXACT = {"head_trust": {"bound": (0.1, 0.0), "bound_loose": (0.1, 0.0)}}


@pytest.fixture(scope="module")
def fixed_inputs():
    mesh, U = data()
    return inputs(mesh, U)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_an_old_model_folder_predicts_what_it_did(kind, fixed_inputs):
    folder = DATA / "schema1_models" / kind
    model = DeformationModel.load(folder)
    got = outputs(model, fixed_inputs)
    with np.load(folder / "expected_outputs.npz", allow_pickle=False) as z:
        expected = {k: z[k] for k in z.files}
    assert sorted(got) == sorted(expected)
    for key, value in expected.items():
        rtol, atol = NEAR_EXACT.get(kind, {}).get(key, COMPILED.get(key, (RTOL, ATOL)))
        np.testing.assert_allclose(got[key], value, rtol=rtol, atol=atol, err_msg=f"{kind}: {key}")
    assert model.has_trust == (kind != "masked") and model.supports_missing_markers == (kind == "masked")


def test_an_old_model_folder_saved_again_is_the_same_model(tmp_path, fixed_inputs):
    old = DeformationModel.load(DATA / "schema1_models" / "head_trust")
    old.save(tmp_path / "again")
    again = DeformationModel.load(tmp_path / "again")
    a, b = outputs(old, fixed_inputs), outputs(again, fixed_inputs)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert again.pca_choice_ == old.pca_choice_ and again.training_ == old.training_
