"""Single-sample prediction latency and batch throughput of a DeformationModel.

Compares, in one run, the in-process paths: the precompiled numpy path (``model.predict``;
for a model with a quadratic head also without it, to show the head's cost), the equivalent
torch module and an onnxruntime session, plus the ridge baseline.
Prints p50/p99 per single prediction (us) and batch throughput (samples/s), with ratios.

    python benchmarks/predict_latency.py [MODEL_FOLDER] [--repeats 5000] [--batch 1000]
        [--versus OTHER_FOLDER]

Without a model folder a model of the paper's size (the phantom, 5 markers, n_w 27,
[128, 64]) is built from random weights: latency does not depend on training.
``--versus`` times another model's ``predict`` (e.g. the same store with another decoder,
``surrogate.decoder``) call by call alternately with the first one's, so that both see the
same machine load, and prints the two p50/p99 and their ratio.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def paper_size_model(ensemble: int = 1):
    """An untrained-but-valid model of the paper's size (random weights, random PCA basis)."""
    from tissuecast.surrogate import DeformationModel, ModelState, NetworkPredictor
    from tissuecast.surrogate.weights import MLPWeights
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
    return DeformationModel.from_state(ModelState(DeformationModel().config, network, np.zeros(0, np.int64),
                                                  {"rule": "random", "n_components": n_w}))


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
    """Print both models' single-sample ``predict`` latency, timed alternately."""
    from tissuecast.surrogate import DeformationModel

    other = DeformationModel.load(other_folder)
    if other.n_markers != model.n_markers:
        raise SystemExit(f"--versus: the models read {model.n_markers} and {other.n_markers} markers")
    t = paired_timings([model.predict, other.predict], singles, repeats) * 1e6
    p50, p99 = np.percentile(t, 50, axis=1), np.percentile(t, 99, axis=1)
    print(f"side by side, alternating calls ({repeats} each):")
    for name, m, a, b in (("first", model, p50[0], p99[0]), ("versus", other, p50[1], p99[1])):
        dec = m.describe()["decoder"]["kind"]
        print(f"  {name:7s} {m.n_components:4d} coefficients, decoder {dec:6s} p50 {a:8.1f} us  p99 {b:8.1f} us")
    print(f"  versus / first: p50 {p50[1] / p50[0]:.2f}x, p99 {p99[1] / p99[0]:.2f}x")


def _torch_and_onnx(model, singles, batch, add) -> tuple[float | None, float | None]:
    """Time the torch module and the ONNX graph (one thread each) where installed; returns their
    batch throughputs (samples/s, None where not installed)."""
    n_d = model.n_markers
    torch_thr = ort_thr = None
    try:
        import torch

        torch.set_num_threads(1)
        net = model.torch_module()
        tin = [torch.as_tensor(s.reshape(1, n_d, 3), dtype=torch.float32) for s in singles]

        def torch_call(x):
            with torch.inference_mode():
                return net(x)

        add("torch  module (1 thread)", torch_call, tin)
        tb = torch.as_tensor(batch, dtype=torch.float32)
        torch_thr = len(batch) / np.median(timings(torch_call, [tb], 20))
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
        feeds = [s.reshape(1, n_d, 3).astype(np.float32) for s in singles]
        extra = {"present": np.ones((1, n_d), np.float32)} if model.supports_missing_markers else {}
        add("onnxruntime (1 thread)", lambda x: sess.run(None, {"markers": x, **extra}), feeds)
        extra_b = {"present": np.ones((len(batch), n_d), np.float32)} if extra else {}
        bf = batch.astype(np.float32)
        ort_thr = len(batch) / np.median(timings(lambda x: sess.run(None, {"markers": x, **extra_b}), [bf], 20))
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
    args = ap.parse_args(argv)

    from tissuecast.surrogate import DeformationModel

    model = DeformationModel.load(args.model) if args.model else paper_size_model(args.ensemble)
    n_d = model.n_markers
    rng = np.random.default_rng(1)
    singles = [rng.normal(scale=5.0, size=3 * n_d) for _ in range(256)]
    rows = []

    def add(name, fn, inputs):
        t = timings(fn, inputs, args.repeats) * 1e6
        rows.append((name, np.percentile(t, 50), np.percentile(t, 99)))

    add("numpy  model.predict", model.predict, singles)
    net = model.network_
    if net.head is not None:  # the same networks without their quadratic head: its cost
        from tissuecast.surrogate import NetworkPredictor

        bare = NetworkPredictor(net.mesh, net.markers, net.basis, net.members)
        add("numpy  model.predict, head left out", bare.predict, singles)
    add("numpy  model.predict_ridge", model.predict_ridge, singles)
    pos = [model.reference_marker_positions + s.reshape(n_d, 3) for s in singles]
    add("numpy  predict_from_positions", model.predict_from_positions, pos)
    batch = rng.normal(scale=5.0, size=(args.batch, n_d, 3))
    torch_thr, ort_thr = _torch_and_onnx(model, singles, batch, add)
    np_thr = args.batch / np.median(timings(model.predict, [batch], 20))

    print(f"model: {model!r}")
    print(f"single-sample prediction, {args.repeats} calls each (in-process)")
    print(f"{'path':34s} {'p50 us':>9s} {'p99 us':>9s} {'p99 / numpy':>12s}")
    ref = rows[0][2]
    for name, p50, p99 in rows:
        print(f"{name:34s} {p50:9.1f} {p99:9.1f} {p99 / ref:12.2f}")
    print(f"target p99 < 100 us: numpy path {'met' if ref < 100 else 'NOT met'} ({ref:.1f} us); paper: < 0.5 s "
          f"(ratio {0.5e6 / ref:,.0f}x)")
    print(f"batch throughput ({args.batch} samples per call):")
    print(f"  numpy        {np_thr:12,.0f} samples/s")
    if torch_thr:
        print(f"  torch        {torch_thr:12,.0f} samples/s   ({torch_thr / np_thr:.2f}x numpy)")
    if ort_thr:
        print(f"  onnxruntime  {ort_thr:12,.0f} samples/s   ({ort_thr / np_thr:.2f}x numpy)")
    if args.versus:
        versus(model, args.versus, singles, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
