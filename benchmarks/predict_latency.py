"""Single-sample prediction latency and batch throughput of a DeformationModel.

Compares, in one run, the in-process paths: the precompiled numpy path (``model.predict``;
for a model with a quadratic head also without it, to show the head's cost), the equivalent
torch module and an onnxruntime session, plus the ridge baseline.
Prints p50/p99 per single prediction (us) and batch throughput (samples/s), with ratios, and
the network alone with its compiled predictor in float32 (as shipped) and in float64, timed
alternately (what the float32 products save).

    python benchmarks/predict_latency.py [MODEL_FOLDER] [--repeats 5000] [--batch 1000]
        [--versus OTHER_FOLDER] [--target-us US] [--ensemble M]

Without a model folder a model of the paper's size (the phantom, 5 markers, n_w 27,
[128, 64]) is built from random weights: latency does not depend on training. A model that
reads tracked instruments (e.g. the embedded preset's retractor) is timed with its inputs: the
marker displacements and instrument poses of its training store's test-1 samples (the store
must be where the model folder records it), every path given both.
``--versus`` times another model's ``predict`` (e.g. the same store with another decoder,
``surrogate.decoder``) call by call alternately with the first one's, so that both see the
same machine load, and prints the two p50/p99 and their ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np


#: Scale of the random marker displacements of a model without a store (mm).
RANDOM_SCALE = 5.0


def paper_size_model(ensemble: int = 1):
    """An untrained-but-valid model of the paper's size (random weights, random PCA basis)."""
    from tissuecast.surrogate import DeformationModel, ModelState, NetworkPredictor
    from tissuecast.surrogate.weights import MLPWeights
    from tissuecast.surrogate.gate import InputGate
    from tissuecast.surrogate.pca import PCABasis

    from tissuecast.mesh.phantom import phantom

    rng = np.random.default_rng(0)
    mesh = phantom()
    n, n_w, n_d, hidden = mesh.n_vertices, 27, 5, (128, 64)
    q, _ = np.linalg.qr(rng.normal(size=(3 * n, n_w)))
    basis = PCABasis(mean=rng.normal(size=3 * n), components=q.T.copy(), singular_values=np.ones(n_w), n_samples=1600)
    members = []
    for _ in range(ensemble):
        sizes = (3 * n_d, *hidden, n_w)
        members.append(MLPWeights(
            weights=tuple(rng.normal(size=(b, a)).astype(np.float32) / np.sqrt(a) for a, b in zip(sizes[:-1], sizes[1:])),
            biases=tuple(rng.normal(size=b).astype(np.float32) * 0.1 for b in sizes[1:]),
            x_mean=np.zeros(3 * n_d, np.float32), x_std=np.full(3 * n_d, 5.0, np.float32),
            y_mean=np.zeros(n_w, np.float32), y_std=np.full(n_w, 10.0, np.float32)))
    network = NetworkPredictor(mesh, [0, 200, 400, 600, 1000], basis, members)
    # the input gate of the inputs the benchmark draws (random displacements of 5 mm scale), so
    # that every call passes the gate's checks as a served frame does
    gate = InputGate.from_inputs(network.markers, network.reference_marker_positions,
                                 rng.normal(scale=RANDOM_SCALE, size=(4000, 3 * n_d)))
    return DeformationModel.from_state(ModelState(DeformationModel().config, network, np.zeros(0, np.int64),
                                                  {"rule": "random", "n_components": n_w}, gate=gate))


def timings(fn, inputs, repeats: int) -> np.ndarray:
    """Per-call wall times (s) of fn(x) over ``repeats`` calls cycling through inputs."""
    for x in inputs[:50]:
        fn(x)
    out = np.empty(repeats)
    k = len(inputs)
    for i in range(repeats):
        x = inputs[i % k]
        t = time.perf_counter()
        fn(x)
        out[i] = time.perf_counter() - t
    return out


def paired_timings(fns, inputs, repeats: int) -> np.ndarray:
    """(len(fns), repeats) wall times (s): the functions called alternately on the same inputs."""
    for x in inputs[:50]:
        for fn in fns:
            fn(x)
    out = np.empty((len(fns), repeats))
    for i in range(repeats):
        x = inputs[i % len(inputs)]
        for j, fn in enumerate(fns):
            t = time.perf_counter()
            fn(x)
            out[j, i] = time.perf_counter() - t
    return out


def versus(model, other_folder: str, singles, repeats: int) -> None:
    """Print both models' single-sample ``predict`` latency, timed alternately (``singles``:
    :func:`model_inputs` of the first)."""
    from tissuecast.surrogate import DeformationModel

    other = DeformationModel.load(other_folder)
    if other.n_markers != model.n_markers:
        raise SystemExit(f"--versus: the models read {model.n_markers} and {other.n_markers} markers")
    if other.auxiliary.names != model.auxiliary.names:
        raise SystemExit(f"--versus: the models read {model.auxiliary.names} and {other.auxiliary.names} beside "
                         "their markers")
    calls = [lambda x, m=m: m.predict(x[0], auxiliary=x[1]) for m in (model, other)]
    t = paired_timings(calls, singles, repeats) * 1e6
    p50, p99 = np.percentile(t, 50, axis=1), np.percentile(t, 99, axis=1)
    print(f"side by side, alternating calls ({repeats} each):")
    for name, m, a, b in (("first", model, p50[0], p99[0]), ("versus", other, p50[1], p99[1])):
        dec = m.describe()["decoder"]["kind"]
        print(f"  {name:7s} {m.n_components:4d} coefficients, decoder {dec:6s} p50 {a:8.1f} us  p99 {b:8.1f} us")
    print(f"  versus / first: p50 {p50[1] / p50[0]:.2f}x, p99 {p99[1] / p99[0]:.2f}x")


def precision_pair(model, singles, repeats: int) -> None:
    """Print the network's single-sample ``predict`` with the compiled predictor as shipped
    (``fastpath.DTYPE``) and compiled in float64, timed alternately, and their largest difference (mm)."""
    from tissuecast.surrogate import NetworkPredictor
    from tissuecast.surrogate.fastpath import DTYPE, CompiledSurrogate

    net = model.network_
    twin = NetworkPredictor(net.mesh, net.markers, net.basis, net.members, net.head, auxiliary=net.auxiliary)
    twin.compiled = CompiledSurrogate(net.members, net.basis, net.head, dtype=np.float64)
    twin.input_gate = dataclasses.replace(net.input_gate)  # its own: the other's memory of the frame it passed
    calls = [lambda x, p=p: p.predict(x[0], auxiliary=x[1]) for p in (net, twin)]
    gap = max(np.abs(calls[0](x) - calls[1](x)).max() for x in singles[:50])
    t = paired_timings(calls, singles, repeats) * 1e6
    p50, p99 = np.percentile(t, 50, axis=1), np.percentile(t, 99, axis=1)
    print(f"the network alone, compiled in {np.dtype(DTYPE).name} (shipped) and in float64, alternating calls "
          f"({repeats} each):")
    for name, a, b in ((np.dtype(DTYPE).name, p50[0], p99[0]), ("float64", p50[1], p99[1])):
        print(f"  {name:8s} p50 {a:8.1f} us  p99 {b:8.1f} us")
    print(f"  float64 / shipped: p50 {p50[1] / p50[0]:.2f}x, p99 {p99[1] / p99[0]:.2f}x; largest difference of the "
          f"fields {gap:.2e} mm")


def model_inputs(model, rng, count: int = 256) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """``count`` single-sample inputs ``(d (3 n_d,) mm, auxiliary (n_a,) or None)``: the model's
    training store's test-1 samples (their marker displacements and instrument poses) where the
    store is at the path the model folder records; else, for a markers-only model, random
    displacements (``RANDOM_SCALE`` mm)."""
    from tissuecast.dataset import open_dataset
    from tissuecast.evaluate.evaluation import auxiliary_values

    if not model.dataset_path or not Path(model.dataset_path).exists():
        if model.auxiliary.width:
            raise SystemExit(f"the model reads {model.auxiliary.names} beside its markers; their values come from "
                             f"its training store, which is not at {model.dataset_path!r}: run the benchmark where "
                             "the model was trained")
        return [(rng.normal(scale=RANDOM_SCALE, size=3 * model.n_markers), None) for _ in range(count)]
    ds = open_dataset(model.dataset_path)
    rows = ds.select("test1")[:count]
    d = model.marker_displacements(np.asarray(ds.displacements[rows], dtype=np.float64)).reshape(len(rows), -1)
    aux = auxiliary_values(model, ds)
    return list(zip(d, [None] * len(rows) if aux is None else aux[rows]))


def _torch_and_onnx(model, singles, batch, add) -> tuple[float | None, float | None]:
    """Time the torch module and the ONNX graph (one thread each) where installed; returns their
    batch throughputs (samples/s, None where not installed). ``singles``: :func:`model_inputs`;
    ``batch``: ``(d (B, n_d, 3), auxiliary (B, n_a) or None)``."""
    n_d = model.n_markers
    torch_thr = ort_thr = None
    d_b, a_b = batch
    try:
        import torch

        torch.set_num_threads(1)
        net = model.torch_module()
        as_t = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
        tin = [(as_t(d.reshape(1, n_d, 3)),) + (() if a is None else (as_t(a.reshape(1, -1)),)) for d, a in singles]

        def torch_call(x):
            with torch.inference_mode():
                return net(*x)

        add("torch  module (1 thread)", torch_call, tin)
        tb = (as_t(d_b),) + (() if a_b is None else (as_t(a_b),))
        torch_thr = len(d_b) / np.median(timings(torch_call, [tb], 20))
    except ImportError:
        pass
    try:
        import onnxruntime as ort

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "m.onnx"
            model.export_onnx(path)
            so = ort.SessionOptions()
            so.intra_op_num_threads = 1
            sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])

        def feed(d, a, rows):
            out = {"markers": d.reshape(rows, n_d, 3).astype(np.float32)}
            if a is not None:
                out["auxiliary"] = a.reshape(rows, -1).astype(np.float32)
            if model.supports_missing_markers:
                out["present"] = np.ones((rows, n_d), np.float32)
            return out

        add("onnxruntime (1 thread)", lambda x: sess.run(None, x), [feed(d, a, 1) for d, a in singles])
        ort_thr = len(d_b) / np.median(timings(lambda x: sess.run(None, x), [feed(d_b, a_b, len(d_b))], 20))
    except ImportError:
        pass
    return torch_thr, ort_thr


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?", help="model folder (default: random paper-size model)")
    ap.add_argument("--repeats", type=int, default=5000)
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--ensemble", type=int, default=1, help="members of the random model")
    ap.add_argument("--versus", help="another model folder, timed alternately with the first")
    ap.add_argument("--target-us", type=float, help="p99 target of model.predict, us; default 1000 for a model "
                    "folder (the embedded preset's target; give 100 for the paper preset's) and 100 for the random "
                    "paper-size model")
    args = ap.parse_args(argv)

    from tissuecast.surrogate import DeformationModel

    model = DeformationModel.load(args.model) if args.model else paper_size_model(args.ensemble)
    n_d = model.n_markers
    rng = np.random.default_rng(1)
    singles = model_inputs(model, rng)
    rows = []

    def add(name, fn, inputs):
        t = timings(fn, inputs, args.repeats) * 1e6
        rows.append((name, np.percentile(t, 50), np.percentile(t, 99)))

    add("numpy  model.predict", lambda x: model.predict(x[0], auxiliary=x[1]), singles)
    net = model.network_
    if net.head is not None:  # the same networks without their quadratic head: its cost
        from tissuecast.surrogate import NetworkPredictor

        bare = NetworkPredictor(net.mesh, net.markers, net.basis, net.members, auxiliary=net.auxiliary)
        add("numpy  model.predict, head left out", lambda x: bare.predict(x[0], auxiliary=x[1]), singles)
    add("numpy  model.predict_ridge", lambda x: model.predict_ridge(x[0]), singles)
    pos = [(model.reference_marker_positions + d.reshape(n_d, 3), a) for d, a in singles]
    add("numpy  predict_from_positions", lambda x: model.predict_from_positions(x[0], auxiliary=x[1]), pos)
    picks = rng.integers(len(singles), size=args.batch)
    batch = (np.stack([singles[i][0] for i in picks]).reshape(args.batch, n_d, 3),
             None if singles[0][1] is None else np.stack([singles[i][1] for i in picks]))
    torch_thr, ort_thr = _torch_and_onnx(model, singles, batch, add)
    np_thr = args.batch / np.median(timings(lambda b: model.predict(b[0], auxiliary=b[1]), [batch], 20))

    print(f"model: {model!r}")
    print(f"single-sample prediction, {args.repeats} calls each (in-process)")
    print(f"{'path':34s} {'p50 us':>9s} {'p99 us':>9s} {'p99 / numpy':>12s}")
    ref = rows[0][2]
    for name, p50, p99 in rows:
        print(f"{name:34s} {p50:9.1f} {p99:9.1f} {p99 / ref:12.2f}")
    target = args.target_us if args.target_us is not None else (1000.0 if args.model else 100.0)
    print(f"target p99 < {target:g} us: numpy path {'met' if ref < target else 'NOT met'} ({ref:.1f} us); paper: "
          f"< 0.5 s (ratio {0.5e6 / ref:,.0f}x)")
    print(f"batch throughput ({args.batch} samples per call):")
    print(f"  numpy        {np_thr:12,.0f} samples/s")
    if torch_thr:
        print(f"  torch        {torch_thr:12,.0f} samples/s   ({torch_thr / np_thr:.2f}x numpy)")
    if ort_thr:
        print(f"  onnxruntime  {ort_thr:12,.0f} samples/s   ({ort_thr / np_thr:.2f}x numpy)")
    precision_pair(model, singles, args.repeats)
    if args.versus:
        versus(model, args.versus, singles, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
