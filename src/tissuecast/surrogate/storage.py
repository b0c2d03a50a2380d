"""Model folders: save, load (never pickle) and ONNX export.

A model folder holds::

    model.json          format, schema, versions, units, markers, fixed vertices,
                        reference marker positions, mesh fingerprint, config, scenario (supports, loads), training summary
    weights.safetensors member{k}.layer{i}.weight/bias and standardisation, float32
    pca.npz             mean (p,), components (n_w, p), singular_values (n_w,), float64
    mesh.npz            points (n, 3) mm, tets (m, 4) 0-based
    head.npz            optional: the quadratic head (tissuecast.surrogate.head): mean, scale,
                        directions, coef, float64
    decoder.npz         optional (surrogate.decoder = "local"): the local components of the decoder
                        (tissuecast.surrogate.decoder) as sparse rows indptr, indices, data and their
                        singular_values; pca.npz then holds its global part
    trust.npz           optional: error bounds and alarm (tissuecast.surrogate.trust), float64
    model.onnx          optional, from export_onnx

Arrays are read with ``allow_pickle=False``; torch.load is never used. The folder holds a
:class:`~.state.ModelState` (``DeformationModel.get_state()`` / ``from_state``): the learned
predictor's parts, the trust layer and the record of the fit; the baselines are rebuilt from them.
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
from .decoder import LocalBasis, describe_decoder, global_part
from .network_predictor import NetworkPredictor
from .pca import PCABasis, PCACurve
from .quadratic import QuadraticRegression
from .state import ModelState
from .trust import TrustLayer
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


def _metadata(state: ModelState) -> dict:
    """``model.json`` of a model state (its ``files`` without the optional trust and ONNX files)."""
    from ..config import config_to_dict

    net = state.network
    b, m0, head, mesh = net.basis, net.members[0], net.head, net.mesh
    return {
        "format": FORMAT,
        "schema": SCHEMA,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "versions": _versions(),
        "units": {"length": "mm", "displacement": "mm"},
        "vertex_ids": "0-based",
        "n_vertices": int(mesh.n_vertices),
        "n_tets": int(mesh.n_tets),
        "mesh_fingerprint": mesh.fingerprint(),
        "markers": net.markers.tolist(),
        "fixed": np.asarray(state.fixed, dtype=np.int64).tolist(),
        "reference_marker_positions": net.reference_marker_positions.tolist(),
        "n_components": int(b.n_components),
        "decoder": describe_decoder(b),
        "network": {"hidden": list(m0.hidden), "n_layers": len(m0.weights), "masked": bool(m0.masked),
                    "ensemble": len(net.members), "input": "marker displacements (n_d, 3) mm, vertex-major",
                    "output": "PCA weights (n_w,) mm",
                    "head": None if head is None else {"kind": "quadratic", "dims": int(len(head.directions))}},
        "surrogate_config": config_to_dict(state.config),
        "config": state.run_config,
        "dataset_path": state.dataset_path,
        "scenario": state.scenario,
        "pca_curve": None if state.pca_curve is None else state.pca_curve.as_dict(),
        "pca_choice": state.pca_choice,
        "training": state.training,
        "files": {"weights": "weights.safetensors", "pca": "pca.npz", "mesh": "mesh.npz",
                  **({"head": "head.npz"} if head is not None else {}),
                  **({"decoder": "decoder.npz"} if isinstance(b, LocalBasis) else {})},
    }


def save_model(state: ModelState, folder, *, onnx: bool = False) -> None:
    """Write a fitted model's state (``DeformationModel.get_state()``) to ``folder`` (created if
    needed; files overwritten)."""
    st = require("safetensors.numpy", "learn", "saving model weights")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    net = state.network
    tensors = {}
    for k, m in enumerate(net.members):
        tensors.update(m.tensors(f"member{k}."))
    st.save_file(tensors, str(out / "weights.safetensors"), metadata={"format": FORMAT, "schema": str(SCHEMA)})
    b = global_part(net.basis)
    np.savez(out / "pca.npz", mean=b.mean, components=b.components, singular_values=b.singular_values,
             n_samples=np.int64(b.n_samples))
    if isinstance(net.basis, LocalBasis):
        np.savez(out / "decoder.npz", **net.basis.arrays())
    np.savez(out / "mesh.npz", points=np.asarray(net.mesh.points, dtype=np.float64),
             tets=np.asarray(net.mesh.tets, dtype=np.int64))
    if net.head is not None:
        np.savez(out / "head.npz", **net.head.arrays(""))
    meta = _metadata(state)
    if state.trust is not None:
        meta["files"]["trust"] = state.trust.save(out)
        meta["trust"] = state.trust.summary()
    if onnx:
        export_onnx(net, out / "model.onnx")
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


def _weights(folder: Path, meta: dict) -> list[MLPWeights]:
    st = require("safetensors.numpy", "learn", "loading model weights")
    net = meta["network"]
    wpath = folder / meta["files"]["weights"]
    if not wpath.is_file():
        raise ModelError(f"model file {str(wpath)!r} is missing; the model folder is incomplete")
    try:
        tensors = st.load_file(str(wpath))
    except Exception as exc:  # safetensors raises its own error types
        raise ModelError(f"model weights {str(wpath)!r} are unreadable: {exc}") from exc
    return [MLPWeights.from_tensors(tensors, f"member{k}.", net["n_layers"], net["masked"]) for k in range(net["ensemble"])]


def _network(folder: Path, meta: dict) -> NetworkPredictor:
    """The learned predictor of a model folder, its mesh checked against the metadata."""
    from ..mesh import TetMesh

    members = _weights(folder, meta)
    p = _npz(folder / meta["files"]["pca"], ["mean", "components", "singular_values", "n_samples"])
    basis = PCABasis(mean=p["mean"], components=p["components"], singular_values=p["singular_values"],
                     n_samples=int(p["n_samples"]))
    m = _npz(folder / meta["files"]["mesh"], ["points", "tets"])
    mesh = TetMesh(m["points"], m["tets"])
    if mesh.fingerprint() != meta["mesh_fingerprint"] or basis.n_features != 3 * mesh.n_vertices:
        raise ModelError(f"the mesh in {str(folder)!r} does not match the model's metadata; the folder is corrupt")
    if meta["files"].get("decoder"):  # folders without it (all before the local decoder) decode with the PCA basis
        basis = LocalBasis.from_arrays(basis, _npz(folder / meta["files"]["decoder"],
                                                   ["indptr", "indices", "data", "singular_values"]))
    head = None
    if meta["files"].get("head"):
        head = QuadraticRegression.from_arrays(_npz(folder / meta["files"]["head"], ["mean", "scale", "directions", "coef"]), "")
    return NetworkPredictor(mesh, meta["markers"], basis, members, head)


def load_model(folder) -> ModelState:
    """Read the state of a model saved by :func:`save_model` (``DeformationModel.from_state`` builds the model)."""
    from ..config import config_from_dict

    folder = Path(folder)
    meta = read_metadata(folder)
    network = _network(folder, meta)
    curve = PCACurve.from_dict(meta["pca_curve"]) if meta.get("pca_curve") else None
    trust = None
    if meta["files"].get("trust"):
        tpath = folder / meta["files"]["trust"]
        if not tpath.is_file():
            raise ModelError(f"model file {str(tpath)!r} is missing; the model folder is incomplete")
        trust = TrustLayer.load(tpath)
    return ModelState(
        config=config_from_dict({"surrogate": meta["surrogate_config"]}).surrogate, network=network,
        fixed=np.asarray(meta["fixed"], dtype=np.int64),
        pca_choice=meta.get("pca_choice") or {"rule": "paper" if curve else "unrecorded",
                                              "n_components": network.n_components},
        pca_curve=curve, trust=trust, training=meta.get("training") or None, run_config=meta.get("config"),
        dataset_path=meta.get("dataset_path"), scenario=meta.get("scenario"), metadata=meta)


def export_onnx(network: NetworkPredictor, path) -> None:
    """Export the learned predictor's full marker -> field network to ONNX (opset 17, dynamic batch)."""
    torch = require("torch", "learn", "ONNX export")
    require("onnx", "learn", "ONNX export")
    net = network.torch_module()
    n_d = network.n_markers
    args = (torch.zeros(1, n_d, 3),)
    names = ["markers"]
    axes = {"markers": {0: "batch"}, "displacement": {0: "batch"}}
    if network.supports_missing_markers:
        args = args + (torch.ones(1, n_d),)
        names.append("present")
        axes["present"] = {0: "batch"}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter is deprecated but fast
        torch.onnx.export(net, args, str(path), input_names=names, output_names=["displacement"],
                          dynamic_axes=axes, opset_version=17, dynamo=False)
