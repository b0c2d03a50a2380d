"""Model folders: save, load (never pickle) and ONNX export.

A model folder holds::

    model.json          format, schema, versions, units, markers, fixed vertices,
                        reference marker positions, mesh fingerprint, config, scenario (supports, loads), training summary
    weights.safetensors member{k}.layer{i}.weight/bias and standardisation, float32
    pca.npz             mean (p,), components (n_w, p), singular_values (n_w,), float64
    mesh.npz            points (n, 3) mm, tets (m, 4) 0-based
    head.npz            optional: the quadratic head (tissuecast.surrogate.head): mean, scale,
                        directions, coef, float64
    trust.npz           optional: error bounds and alarm (tissuecast.surrogate.trust), float64
    model.onnx          optional, from export_onnx

Arrays are read with ``allow_pickle=False``; torch.load is never used.
"""

from __future__ import annotations

import datetime
import json
import platform
import warnings
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import ModelError, require
from .mlp import TrainingSummary
from .pca import PCABasis, PCACurve
from .weights import MLPWeights

__all__ = ["FORMAT", "SCHEMA", "save_model", "load_model", "export_onnx", "read_metadata"]

FORMAT = "tissuecast-model"
SCHEMA = 1


def _versions() -> dict:
    out = {"tissuecast": __version__, "numpy": np.__version__, "python": platform.python_version()}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:  # pragma: no cover - torch is needed to train, not to save
        pass
    return out


def save_model(model, folder, *, onnx: bool = False) -> None:
    """Write ``model`` (fitted) to ``folder`` (created if needed; files overwritten)."""
    from ..config import config_to_dict

    st = require("safetensors.numpy", "learn", "saving model weights")
    model._fitted()
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    tensors = {}
    for k, m in enumerate(model.members_):
        tensors.update(m.tensors(f"member{k}."))
    st.save_file(tensors, str(out / "weights.safetensors"), metadata={"format": FORMAT, "schema": str(SCHEMA)})
    b = model.pca_
    np.savez(out / "pca.npz", mean=b.mean, components=b.components, singular_values=b.singular_values,
             n_samples=np.int64(b.n_samples))
    np.savez(out / "mesh.npz", points=np.asarray(model.mesh_.points, dtype=np.float64),
             tets=np.asarray(model.mesh_.tets, dtype=np.int64))
    m0 = model.members_[0]
    head = getattr(model, "head_", None)
    if head is not None:
        np.savez(out / "head.npz", **head.arrays(""))
    meta = {
        "format": FORMAT,
        "schema": SCHEMA,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "versions": _versions(),
        "units": {"length": "mm", "displacement": "mm"},
        "vertex_ids": "0-based",
        "n_vertices": int(model.mesh_.n_vertices),
        "n_tets": int(model.mesh_.n_tets),
        "mesh_fingerprint": model.mesh_.fingerprint(),
        "markers": model.markers_.tolist(),
        "fixed": model.fixed_.tolist(),
        "reference_marker_positions": model.reference_marker_positions.tolist(),
        "n_components": int(b.n_components),
        "network": {"hidden": list(m0.hidden), "n_layers": len(m0.weights), "masked": bool(m0.masked),
                    "ensemble": len(model.members_), "input": "marker displacements (n_d, 3) mm, vertex-major",
                    "output": "PCA weights (n_w,) mm",
                    "head": None if head is None else {"kind": "quadratic", "dims": int(len(head.directions))}},
        "surrogate_config": config_to_dict(model.config),
        "config": model.run_config,
        "dataset_path": model.dataset_path,
        "scenario": model.scenario,
        "pca_curve": None if model.pca_curve_ is None else model.pca_curve_.as_dict(),
        "pca_choice": getattr(model, "pca_choice_", None),
        "training": getattr(model, "training_", None),
        "files": {"weights": "weights.safetensors", "pca": "pca.npz", "mesh": "mesh.npz",
                  **({"head": "head.npz"} if head is not None else {})},
    }
    if getattr(model, "trust_", None) is not None:
        meta["files"]["trust"] = model.trust_.save(out)
        meta["trust"] = model.trust_.summary()
    if onnx:
        export_onnx(model, out / "model.onnx")
        meta["files"]["onnx"] = "model.onnx"
    (out / "model.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")


def read_metadata(folder) -> dict:
    """The checked ``model.json`` of a model folder."""
    p = Path(folder) / "model.json"
    if not p.is_file():
        raise ModelError(f"{str(folder)!r} is not a model folder (no model.json); train one with `tissuecast train`")
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelError(f"{str(p)!r} is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise ModelError(f"{str(p)!r} is not a tissuecast model (format {found!r})")
    if meta.get("schema") != SCHEMA:
        raise ModelError(
            f"model schema {meta.get('schema')!r} (written by tissuecast {meta.get('versions', {}).get('tissuecast')}) "
            f"is not supported by tissuecast {__version__} (schema {SCHEMA}); re-train the model with this version"
        )
    return meta


def _npz(path: Path, keys) -> dict:
    if not path.is_file():
        raise ModelError(f"model file {str(path)!r} is missing; the model folder is incomplete")
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in keys}
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:  # empty, truncated, random bytes
        cause = "not a NumPy .npz archive" if "pickle" in str(exc) else f"{type(exc).__name__}: {exc}"  # never unpickled
        raise ModelError(f"model file {str(path)!r} is unreadable or incomplete ({cause}); the model folder is "
                         "corrupt: save or copy it again") from exc


def load_model(cls, folder):
    """Rebuild a model saved by :func:`save_model`."""
    from ..config import config_from_dict
    from ..mesh import TetMesh

    st = require("safetensors.numpy", "learn", "loading model weights")
    folder = Path(folder)
    meta = read_metadata(folder)
    net = meta["network"]
    wpath = folder / meta["files"]["weights"]
    if not wpath.is_file():
        raise ModelError(f"model file {str(wpath)!r} is missing; the model folder is incomplete")
    try:
        tensors = st.load_file(str(wpath))
    except Exception as exc:  # safetensors raises its own error types
        raise ModelError(f"model weights {str(wpath)!r} are unreadable: {exc}") from exc
    members = [MLPWeights.from_tensors(tensors, f"member{k}.", net["n_layers"], net["masked"]) for k in range(net["ensemble"])]
    p = _npz(folder / meta["files"]["pca"], ["mean", "components", "singular_values", "n_samples"])
    basis = PCABasis(mean=p["mean"], components=p["components"], singular_values=p["singular_values"],
                     n_samples=int(p["n_samples"]))
    m = _npz(folder / meta["files"]["mesh"], ["points", "tets"])
    mesh = TetMesh(m["points"], m["tets"])
    if mesh.fingerprint() != meta["mesh_fingerprint"] or basis.n_features != 3 * mesh.n_vertices:
        raise ModelError(f"the mesh in {str(folder)!r} does not match the model's metadata; the folder is corrupt")
    sc = config_from_dict({"surrogate": meta["surrogate_config"]}).surrogate
    model = cls(sc)
    model.run_config = meta.get("config")
    model.dataset_path = meta.get("dataset_path")
    model.scenario = meta.get("scenario")
    curve = PCACurve.from_dict(meta["pca_curve"]) if meta.get("pca_curve") else None
    model.pca_choice_ = meta.get("pca_choice") or {"rule": "paper" if curve else "unrecorded",
                                                   "n_components": basis.n_components}
    head = None
    if meta["files"].get("head"):
        from .quadratic import QuadraticRegression

        head = QuadraticRegression.from_arrays(_npz(folder / meta["files"]["head"], ["mean", "scale", "directions", "coef"]), "")
    model._set_state(mesh=mesh, markers=meta["markers"], fixed=meta["fixed"], basis=basis, members=members, curve=curve,
                     head=head)
    if meta.get("training"):
        model.training_ = meta["training"]
        model.summaries_ = [TrainingSummary(**{k: (tuple(map(tuple, v)) if k == "valid_history" else v) for k, v in s.items()})
                            for s in meta["training"].get("members", [])]
    model.trust_ = None
    if meta["files"].get("trust"):
        from .trust import TrustLayer

        tpath = folder / meta["files"]["trust"]
        if not tpath.is_file():
            raise ModelError(f"model file {str(tpath)!r} is missing; the model folder is incomplete")
        model.trust_ = TrustLayer.load(tpath)
    model.metadata_ = meta
    return model


def export_onnx(model, path) -> None:
    """Export the full marker -> field network to ONNX (opset 17, dynamic batch)."""
    torch = require("torch", "learn", "ONNX export")
    require("onnx", "learn", "ONNX export")
    model._fitted()
    net = model.torch_module()
    n_d = model.n_markers
    args = (torch.zeros(1, n_d, 3),)
    names = ["markers"]
    axes = {"markers": {0: "batch"}, "displacement": {0: "batch"}}
    if model.supports_missing_markers:
        args = args + (torch.ones(1, n_d),)
        names.append("present")
        axes["present"] = {0: "batch"}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter is deprecated but fast
        torch.onnx.export(net, args, str(path), input_names=names, output_names=["displacement"],
                          dynamic_axes=axes, opset_version=17, dynamo=False)
