"""Predicting with one marker untracked by a set of sub-models (one network per dropped marker).

A :class:`SubModelSet` holds the full :class:`DeformationModel` (all n_d markers) and n_d
sub-models, sub-model i trained on the same data without marker i. A prediction with no
marker missing uses the full model; with marker i missing it uses sub-model i on the other
markers. Compared with one network trained with marker dropout (``marker_dropout > 0``,
``predict(..., missing=...)``) it costs n_d extra trainings and n_d times the storage, but
each sub-model is a plain network of the paper's kind; ``benchmarks/or_robustness.py``
measures both. Two or more missing markers are refused.

The set is a :class:`~.field_predictor.FieldPredictor` (it supports missing markers, and has
uncertainty when every model is an ensemble), so ``tissuecast serve`` can serve a saved set directly.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import ModelError
from .field_predictor import FieldPredictor
from .inputs import missing_mask
from .model import DeformationModel

__all__ = ["SubModelSet", "load_model_folder", "MANIFEST"]

MANIFEST = "submodels.json"
_FORMAT = "tissuecast-submodels"


class SubModelSet(FieldPredictor):
    """The full model plus one sub-model per dropped marker.

    Args:
        full: model using every marker.
        subs: n_d models; ``subs[i]`` uses ``full.markers`` without entry i, in order.
    """

    def __init__(self, full: DeformationModel, subs: list[DeformationModel]):
        markers = full.markers
        if len(subs) != len(markers):
            raise ModelError(f"need one sub-model per marker ({len(markers)}), got {len(subs)}")
        for i, sub in enumerate(subs):
            if not np.array_equal(sub.markers, np.delete(markers, i)) or sub.n_vertices != full.n_vertices:
                raise ModelError(f"sub-model {i} must use markers {np.delete(markers, i).tolist()} on the same mesh, "
                                 f"got markers {sub.markers.tolist()} on {sub.n_vertices} vertices")
        self.full, self.subs = full, list(subs)
        self.input_gate = full.input_gate  # the full model's input gate checks the tracked markers

    @classmethod
    def fit(cls, displacements, markers, *, mesh, fixed=(), train_idx=None, valid_idx=None, config=None,
            **overrides) -> "SubModelSet":
        """Fit the full model, then each sub-model with the full model's number of PCA components.

        Arguments as :meth:`DeformationModel.fit`; ``config``/``overrides`` as its constructor.
        """
        markers = np.asarray(markers, dtype=np.int64)
        kwargs = dict(mesh=mesh, fixed=fixed, train_idx=train_idx, valid_idx=valid_idx)
        full = DeformationModel(config, **overrides).fit(displacements, markers, **kwargs)
        overrides = {**overrides, "n_components": full.n_components}
        subs = [DeformationModel(config, **overrides).fit(displacements, np.delete(markers, i), **kwargs)
                for i in range(len(markers))]
        return cls(full, subs)

    # ------------------------------------------------------------------ the predictor protocol
    name = "submodels"
    supports_missing_markers = True

    @property
    def mesh(self):
        return self.full.mesh

    @property
    def markers(self) -> np.ndarray:
        return self.full.markers

    @property
    def fixed(self) -> np.ndarray:
        return self.full.fixed

    @property
    def ensemble_size(self) -> int:
        """The smallest ensemble among the full model and the sub-models."""
        return min(m.ensemble_size for m in (self.full, *self.subs))

    @property
    def has_uncertainty(self) -> bool:
        return all(m.has_uncertainty for m in (self.full, *self.subs))

    def _route(self, marker_displacements, missing):
        """-> (d (B, n_d, 3) mm, which (B,) int: -1 = full model, i = sub-model i, single?)."""
        n_d = self.n_markers
        d = np.asarray(marker_displacements, dtype=np.float64)
        single = d.shape in ((3 * n_d,), (n_d, 3))
        if single:
            d = d.reshape(1, n_d, 3)
        elif d.ndim == 2 and d.shape[1] == 3 * n_d:
            d = d.reshape(-1, n_d, 3)
        elif not (d.ndim == 3 and d.shape[1:] == (n_d, 3)):
            raise ModelError(f"marker displacements must have shape ({3 * n_d},), ({n_d}, 3), (B, {n_d}, 3) or "
                             f"(B, {3 * n_d}) mm, got {np.shape(marker_displacements)}")
        mask = np.zeros((len(d), n_d), dtype=bool) if missing is None else missing_mask(missing, len(d), n_d)
        if (mask.sum(axis=1) > 1).any():
            raise ModelError("a SubModelSet predicts with at most one untracked marker per sample")
        which = np.where(mask.any(axis=1), mask.argmax(axis=1), -1)
        return d, which, single

    def _apply(self, predict, marker_displacements, missing):
        """``predict(model, inputs)`` of each sample's model (full, or sub-model i without marker
        i), gathered in sample order; a tuple result gives a tuple of gathered arrays."""
        d, which, single = self._route(marker_displacements, missing)
        outputs = None
        for k in np.unique(which):
            rows = np.flatnonzero(which == k)
            model = self.full if k < 0 else self.subs[k]
            inputs = d[rows] if k < 0 else np.delete(d[rows], k, axis=1)
            result = predict(model, inputs)
            result = result if isinstance(result, tuple) else (result,)
            if outputs is None:
                outputs = [np.empty((len(d), *r.shape[1:])) for r in result]
            for out, r in zip(outputs, result):
                out[rows] = r
        outputs = [o[0] for o in outputs] if single else outputs
        return outputs[0] if len(outputs) == 1 else tuple(outputs)

    def predict(self, marker_displacements, *, missing=None, auxiliary=None) -> np.ndarray:
        """(n, 3) or (B, n, 3) mm from marker displacements (as DeformationModel.predict);
        ``missing``: at most one marker index per sample, or a bool mask. The set reads the
        markers only (``auxiliary`` is ignored; its models' instruments count as absent)."""
        return self._apply(lambda model, x: model.predict(x), marker_displacements, missing)

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None) -> np.ndarray:
        return self.predict(d.reshape(len(d), -1, 3), missing=missing)

    def predict_with_uncertainty(self, marker_displacements, *, missing=None,
                                 auxiliary=None) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble mean (n, 3) mm and per-vertex sigma (n,) mm; every member must be an ensemble
        (``auxiliary`` is ignored, as in :meth:`predict`)."""
        return self._apply(lambda model, x: model.predict_with_uncertainty(x), marker_displacements, missing)

    # ------------------------------------------------------------------ persistence
    def save(self, folder) -> None:
        """Write ``full/``, ``without_0/`` ... (DeformationModel folders) and a JSON manifest."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.full.save(folder / "full")
        for i, sub in enumerate(self.subs):
            sub.save(folder / f"without_{i}")
        manifest = {"format": _FORMAT, "version": 1, "markers": self.markers.tolist(),
                    "folders": ["full"] + [f"without_{i}" for i in range(len(self.subs))]}
        (folder / MANIFEST).write_text(json.dumps(manifest, indent=2))

    @classmethod
    def load(cls, folder) -> "SubModelSet":
        """Read a folder written by :meth:`save`."""
        folder = Path(folder)
        try:
            manifest = json.loads((folder / MANIFEST).read_text())
        except (OSError, ValueError) as exc:
            raise ModelError(f"{folder} is not a SubModelSet folder ({MANIFEST} unreadable: {exc})") from exc
        if manifest.get("format") != _FORMAT or manifest.get("version") != 1:
            raise ModelError(f"{folder / MANIFEST}: unknown format {manifest.get('format')!r} version "
                             f"{manifest.get('version')!r}; expected {_FORMAT!r} version 1")
        models = [DeformationModel.load(folder / name) for name in manifest["folders"]]
        return cls(models[0], models[1:])

    def __repr__(self) -> str:
        return f"SubModelSet(full={self.full!r}, {len(self.subs)} sub-models)"


def load_model_folder(folder) -> DeformationModel | SubModelSet:
    """Load a DeformationModel folder, or a SubModelSet folder (one holding ``submodels.json``)."""
    folder = Path(folder)
    return SubModelSet.load(folder) if (folder / MANIFEST).is_file() else DeformationModel.load(folder)
