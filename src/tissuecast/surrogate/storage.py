"""Model folders: save, load (never pickle) and ONNX export.

A model folder holds::

    model.json          format, schema, versions, units, markers, fixed vertices,
                        reference marker positions, mesh fingerprint, config, scenario (supports, loads), training summary,
                        input gate (each marker's largest simulated displacement and each marker pair's
                        simulated stretch range, tissuecast.surrogate.gate; absent in older folders: derived)
    weights.safetensors member{k}.layer{i}.weight/bias and standardisation, float32
    pca.npz             mean (p,), components (n_w, p), singular_values (n_w,), float64
    mesh.npz            points (n, 3) mm, tets (m, 4) 0-based
    head.npz            optional: the quadratic head (tissuecast.surrogate.head): mean, scale,
                        directions, coef, float64
    decoder.npz         optional (surrogate.decoder = "local"): the local components of the decoder
                        (tissuecast.surrogate.decoder) as sparse rows indptr, indices, data and their
                        singular_values; pca.npz then holds its global part
    trust.npz           optional: error bounds and alarm (tissuecast.surrogate.trust), float64
    model.onnx          optional, from export_onnx (a model with a nominal expert: the routed graph of both)
    fallback/           models with tracked instruments as inputs (tissuecast.surrogate.fallback):
                        the fallback without them, as weights.safetensors, pca.npz, head.npz,
                        trust.npz (and model.onnx) above; model.json's "fallback" describes it
    nominal_expert/     models with a nominal expert (tissuecast.surrogate.experts): the expert's own
                        model folder; model.json's "nominal_expert" holds its gate (JSON)

``model.json``'s ``auxiliary`` lists the auxiliary inputs (tissuecast.surrogate.auxiliary: the
instruments with their OpenIGTLink devices, the measured parameters, every input's name and
unit); folders without it read the markers only.

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
from ..markers import write_markers_markups
from .decoder import LocalBasis, describe_decoder, global_part
from .experts import ExpertGate, RouteCalibration, RoutedNetworks, routed_networks
from .gate import InputGate
from .network_predictor import NetworkPredictor
from .auxiliary import AuxiliaryInputs
from .pca import PCABasis, PCACurve
from .quadratic import QuadraticRegression
from .state import ModelState
from .trust import TrustLayer
from .weights import MLPWeights

__all__ = ["FORMAT", "SCHEMA", "save_model", "load_model", "export_onnx", "read_metadata"]

FORMAT = "tissuecast-model"
SCHEMA = 1
#: Sub-folder of the fallback network of a model with tracked instruments.
FALLBACK_FOLDER = "fallback"
#: Sub-folder of the nominal expert of a model that has one.
EXPERT_FOLDER = "nominal_expert"
#: The pair's per-route conformal scores of its bounds (:class:`~.experts.RouteCalibration`).
ROUTES_FILE = "expert_routes.npz"
#: The model's markers and fixed vertices as 3D Slicer markups (LPS), beside the model files.
MARKUPS_FILE = "markers.mrk.json"
#: Files of the layout above that a fitted model may or may not write (removed before a save, so
#: that a folder saved over an earlier model holds none of that model's parts).
_OPTIONAL_FILES = ("head.npz", "decoder.npz", "trust.npz", "model.onnx", ROUTES_FILE, MARKUPS_FILE)


def _versions() -> dict:
    out = {"tissuecast": __version__, "numpy": np.__version__, "python": platform.python_version()}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:  # pragma: no cover - torch is needed to train, not to save
        pass
    return out


def _network_record(net: NetworkPredictor) -> dict:
    """``model.json``'s description of a network's parts."""
    m0, head = net.members[0], net.head
    return {"hidden": list(m0.hidden), "n_layers": len(m0.weights), "masked": bool(m0.masked),
            "ensemble": len(net.members), "input": "marker displacements (n_d, 3) mm, vertex-major"
            + (", then the auxiliary inputs" if m0.n_auxiliary else ""),
            "output": "PCA weights (n_w,) mm", "n_auxiliary": int(m0.n_auxiliary),
            "head": None if head is None else {"kind": "quadratic", "dims": int(len(head.directions))},
            "activation": m0.activation}


def _metadata(state: ModelState) -> dict:
    """``model.json`` of a model state (its ``files`` without the optional trust and ONNX files)."""
    from ..config import config_to_dict

    net = state.network
    b, head, mesh = net.basis, net.head, net.mesh
    record = _network_record(net)
    if not record["n_auxiliary"]:  # folders of markers-only models read as before
        del record["n_auxiliary"]
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
        "network": record,
        "surrogate_config": config_to_dict(state.config),
        "config": state.run_config,
        "dataset_path": state.dataset_path,
        "scenario": state.scenario,
        "pca_curve": None if state.pca_curve is None else state.pca_curve.as_dict(),
        "pca_choice": state.pca_choice,
        "training": state.training,
        "input_gate": None if state.gate is None else state.gate.as_dict(),
        "files": {"weights": "weights.safetensors", "pca": "pca.npz", "mesh": "mesh.npz",
                  **({"head": "head.npz"} if head is not None else {}),
                  **({"decoder": "decoder.npz"} if isinstance(b, LocalBasis) else {})},
    }


def _write_network(net: NetworkPredictor, out: Path) -> None:
    """A network's weights, PCA basis, local decoder and head (``weights.safetensors``, ``pca.npz``,
    ``decoder.npz``, ``head.npz``) into ``out``."""
    st = require("safetensors.numpy", "learn", "saving model weights")
    out.mkdir(parents=True, exist_ok=True)
    tensors = {}
    for k, m in enumerate(net.members):
        tensors.update(m.tensors(f"member{k}."))
    st.save_file(tensors, str(out / "weights.safetensors"), metadata={"format": FORMAT, "schema": str(SCHEMA)})
    b = global_part(net.basis)
    np.savez(out / "pca.npz", mean=b.mean, components=b.components, singular_values=b.singular_values,
             n_samples=np.int64(b.n_samples))
    if isinstance(net.basis, LocalBasis):
        np.savez(out / "decoder.npz", **net.basis.arrays())
    if net.head is not None:
        np.savez(out / "head.npz", **net.head.arrays(""))


def save_model(state: ModelState, folder, *, onnx: bool = False, markups: bool = True) -> None:
    """Write a fitted model's state (``DeformationModel.get_state()``) to ``folder`` (created if
    needed; files overwritten), with ``markups`` its markers and fixed vertices as 3D Slicer
    markups (:data:`MARKUPS_FILE`, LPS: the points to track, in the model's order)."""
    out = Path(folder)
    _clear_earlier_model(out)
    net = state.network
    _write_network(net, out)
    np.savez(out / "mesh.npz", points=np.asarray(net.mesh.points, dtype=np.float64),
             tets=np.asarray(net.mesh.tets, dtype=np.int64))
    meta = _metadata(state)
    if markups:
        write_markers_markups(out / MARKUPS_FILE, net.mesh, net.markers, state.fixed)
        meta["files"]["markups"] = MARKUPS_FILE
    if state.trust is not None:
        meta["files"]["trust"] = state.trust.save(out)
        meta["trust"] = state.trust.summary()
    if onnx:
        export_onnx(net if state.expert is None else routed_networks(state), out / "model.onnx")
        meta["files"]["onnx"] = "model.onnx"
    if net.auxiliary.width:
        meta["auxiliary"] = net.auxiliary.as_dict()
    if state.fallback is not None:
        meta["fallback"] = _save_fallback(state, out / FALLBACK_FOLDER, onnx)
    if state.expert is not None:
        save_model(state.expert, out / EXPERT_FOLDER, markups=False)  # the same markers
        meta["nominal_expert"] = {"folder": EXPERT_FOLDER, "gate": state.expert_gate.as_dict()}
        if state.expert_routes is not None:
            np.savez(out / ROUTES_FILE, **state.expert_routes.arrays())
            meta["nominal_expert"].update(routes=ROUTES_FILE, route_samples=state.expert_routes.summary())
    (out / "model.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")


def _clear_earlier_model(out: Path) -> None:
    """Remove from ``out`` the optional parts of an earlier model saved there (its head, decoder,
    trust layer, graph, fallback and nominal expert): the layout's own names only."""
    for name in _OPTIONAL_FILES:
        (out / name).unlink(missing_ok=True)
    for sub in (out / FALLBACK_FOLDER, out / EXPERT_FOLDER):
        if sub.is_dir():
            _clear_earlier_model(sub)
            for name in _OPTIONAL_FILES + ("weights.safetensors", "pca.npz", "mesh.npz", "model.json"):
                (sub / name).unlink(missing_ok=True)
            try:
                sub.rmdir()
            except OSError:  # it holds files that are not the layout's: left as they are
                pass


def _save_fallback(state: ModelState, out: Path, onnx: bool) -> dict:
    """Write the fallback network (and its trust layer) into ``out``; its ``model.json`` record."""
    fb = state.fallback
    _write_network(fb, out)
    files = {"weights": "weights.safetensors", "pca": "pca.npz", **({"head": "head.npz"} if fb.head is not None else {}),
             **({"decoder": "decoder.npz"} if isinstance(fb.basis, LocalBasis) else {})}
    record = {"folder": FALLBACK_FOLDER, "n_components": int(fb.n_components), "network": _network_record(fb),
              "auxiliary": fb.auxiliary.as_dict()}
    if state.fallback_trust is not None:
        files["trust"] = state.fallback_trust.save(out)
        record["trust"] = state.fallback_trust.summary()
    if onnx:
        export_onnx(fb if state.expert is None else routed_networks(state, fallback=True), out / "model.onnx")
        files["onnx"] = "model.onnx"
    record["files"] = files
    return record


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


def _npz(path: Path, keys=None) -> dict:
    """The arrays ``keys`` (None: every one) of a model folder's ``.npz`` file, never unpickled.

    Raises:
        ModelError: a missing, empty, truncated or random-bytes file, or a key it lacks.
    """
    if not path.is_file():
        raise ModelError(f"model file {str(path)!r} is missing; the model folder is incomplete")
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in (z.files if keys is None else keys)}
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
    return [MLPWeights.from_tensors(tensors, f"member{k}.", net["n_layers"], net["masked"], net.get("n_auxiliary", 0),
                                      net.get("activation", "relu"))
            for k in range(net["ensemble"])]


def _network_parts(folder: Path, meta: dict, mesh, auxiliary: AuxiliaryInputs) -> NetworkPredictor:
    """A network of a (sub-)folder whose record ``meta`` has ``network`` and ``files``."""
    members = _weights(folder, meta)
    p = _npz(folder / meta["files"]["pca"], ["mean", "components", "singular_values", "n_samples"])
    basis = PCABasis(mean=p["mean"], components=p["components"], singular_values=p["singular_values"],
                     n_samples=int(p["n_samples"]))
    if basis.n_features != 3 * mesh.n_vertices:
        raise ModelError(f"the PCA basis in {str(folder)!r} does not match the model's mesh; the folder is corrupt")
    if meta["files"].get("decoder"):  # folders without it (all before the local decoder) decode with the PCA basis
        basis = LocalBasis.from_arrays(basis, _npz(folder / meta["files"]["decoder"],
                                                   ["indptr", "indices", "data", "singular_values"]))
    head = None
    if meta["files"].get("head"):
        head = QuadraticRegression.from_arrays(_npz(folder / meta["files"]["head"], ["mean", "scale", "directions", "coef"]), "")
    return NetworkPredictor(mesh, meta["markers"], basis, members, head, auxiliary)


def _network(folder: Path, meta: dict) -> NetworkPredictor:
    """The learned predictor of a model folder, its mesh checked against the metadata."""
    from ..mesh import TetMesh

    m = _npz(folder / meta["files"]["mesh"], ["points", "tets"])
    mesh = TetMesh(m["points"], m["tets"])
    if mesh.fingerprint() != meta["mesh_fingerprint"]:
        raise ModelError(f"the mesh in {str(folder)!r} does not match the model's metadata; the folder is corrupt")
    return _network_parts(folder, meta, mesh, AuxiliaryInputs.from_dict(meta.get("auxiliary")))


def _trust(path: Path) -> TrustLayer:
    arrays = _npz(path)
    try:
        return TrustLayer.from_arrays(arrays)
    except (KeyError, ValueError) as exc:  # a file of other arrays
        raise ModelError(f"model file {str(path)!r} is unreadable or incomplete ({type(exc).__name__}: {exc}); the "
                         "model folder is corrupt: save or copy it again") from exc


def _fallback(folder: Path, meta: dict, network: NetworkPredictor) -> tuple[NetworkPredictor | None, TrustLayer | None]:
    """The fallback network (and its trust layer) of a model folder, or ``(None, None)``."""
    record = meta.get("fallback")
    if not record:
        return None, None
    sub = folder / record.get("folder", FALLBACK_FOLDER)
    parts = {"network": record["network"], "files": record["files"], "markers": meta["markers"]}
    net = _network_parts(sub, parts, network.mesh, AuxiliaryInputs.from_dict(record.get("auxiliary")))
    trust = _trust(sub / record["files"]["trust"]) if record["files"].get("trust") else None
    return net, trust


def load_model(folder) -> ModelState:
    """Read the state of a model saved by :func:`save_model` (``DeformationModel.from_state`` builds the model)."""
    from ..config import config_from_dict

    folder = Path(folder)
    meta = read_metadata(folder)
    network = _network(folder, meta)
    curve = PCACurve.from_dict(meta["pca_curve"]) if meta.get("pca_curve") else None
    trust = _trust(folder / meta["files"]["trust"]) if meta["files"].get("trust") else None
    fallback, fallback_trust = _fallback(folder, meta, network)
    expert, expert_gate, expert_routes = None, None, None
    if meta.get("nominal_expert"):
        record = meta["nominal_expert"]
        expert, expert_gate = load_model(folder / record["folder"]), ExpertGate.from_dict(record["gate"])
        if record.get("routes"):
            expert_routes = RouteCalibration.from_arrays(_npz(folder / record["routes"], ("expert", "model")))
    return ModelState(
        config=config_from_dict({"surrogate": meta["surrogate_config"]}).surrogate, network=network,
        fixed=np.asarray(meta["fixed"], dtype=np.int64),
        pca_choice=meta.get("pca_choice") or {"rule": "paper" if curve else "unrecorded",
                                              "n_components": network.n_components},
        pca_curve=curve, trust=trust, training=meta.get("training") or None, run_config=meta.get("config"),
        dataset_path=meta.get("dataset_path"), scenario=meta.get("scenario"), metadata=meta, fallback=fallback,
        fallback_trust=fallback_trust, gate=_gate(network, meta), expert=expert, expert_gate=expert_gate,
        expert_routes=expert_routes)


def _gate(network: NetworkPredictor, meta: dict) -> InputGate | None:
    """The stored input gate, or None for folders written before it (then derived: :func:`.state.gate_of`)."""
    doc = meta.get("input_gate")
    if not doc:
        return None
    try:
        return InputGate.from_dict(network.markers, network.reference_marker_positions, doc)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"the input gate in model.json is incomplete: {exc}; the folder is corrupt") from exc


def export_onnx(network: NetworkPredictor | RoutedNetworks, path) -> None:
    """Export the learned predictor's full marker -> field network (or a pair's routed graph) to
    ONNX (opset 17, dynamic batch): inputs ``markers`` (B, n_d, 3) marker displacements (not
    positions) mm, ``auxiliary`` (B, n_a) with auxiliary inputs, ``present`` (B, n_d) for masked
    models; output ``displacement`` (B, n, 3) mm. The file's ``metadata_props`` say so, with the
    marker vertex ids and reference positions; the graph checks nothing (no gate, bounds, alarm)."""
    torch = require("torch", "learn", "ONNX export")
    require("onnx", "learn", "ONNX export")
    net = network.torch_module()
    n_d = network.n_markers
    args = (torch.zeros(1, n_d, 3),)
    names = ["markers"]
    axes = {"markers": {0: "batch"}, "displacement": {0: "batch"}}
    if network.auxiliary.width:
        args = args + (torch.zeros(1, network.auxiliary.width),)
        names.append("auxiliary")
        axes["auxiliary"] = {0: "batch"}
    if network.supports_missing_markers:
        args = args + (torch.ones(1, n_d),)
        names.append("present")
        axes["present"] = {0: "batch"}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter is deprecated but fast
        torch.onnx.export(net, args, str(path), input_names=names, output_names=["displacement"],
                          dynamic_axes=axes, opset_version=17, dynamo=False)
    _describe_graph(path, network)


def _describe_graph(path, network: NetworkPredictor | RoutedNetworks) -> None:
    """Write what a consumer of the ONNX file alone needs into its metadata (``metadata_props``)
    and doc string: what the inputs are (displacements, not positions), units, frame, marker
    order, and that the graph checks nothing."""
    import onnx

    graph = onnx.load(str(path))
    markers = np.asarray(network.markers, dtype=np.int64)
    props = {
        "tissuecast_version": __version__,
        "markers": "(B, n_d, 3) float32: each marker's displacement from its reference position (not its position), mm, "
                   "in the model's (the scan's) LPS frame, in marker_vertex_ids order",
        "marker_vertex_ids": json.dumps(markers.tolist()),
        "reference_marker_positions_mm": json.dumps(np.round(network.mesh.points[markers], 6).tolist()),
        "displacement": "(B, n, 3) float32: every mesh vertex's displacement, mm, LPS, vertex ids 0-based",
        "checks": "none: the graph has no input gate, error bounds or alarm (tissuecast's Python model and serve give them)",
    }
    if network.auxiliary.width:
        props["auxiliary"] = f"(B, {network.auxiliary.width}) float32: " + ", ".join(
            f"{n} [{u}]" for n, u in zip(network.auxiliary.names, network.auxiliary.units))
    if network.supports_missing_markers:
        props["present"] = "(B, n_d) float32: 1 where the marker is tracked, 0 where it is not (its markers row ignored)"
    onnx.helper.set_model_props(graph, props)
    graph.doc_string = (f"tissuecast {__version__}: marker displacements -> displacement field of a {len(network.mesh.points)}-"
                        f"vertex mesh; inputs and units in metadata_props")
    onnx.save(graph, str(path))
