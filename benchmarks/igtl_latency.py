"""OpenIGTLink round-trip latency of `tissuecast serve` on the phantom (target: p99 < 1 ms).

A model with the paper's architecture ([128, 64], n_w = 27, 5 markers) is fitted on smooth
synthetic fields on the phantom (accuracy is irrelevant here, only the sizes matter) and
saved; ``tissuecast serve`` runs it in a separate process on 127.0.0.1; a blocking client
(pyigtl packing, own socket, CRC verified, POLYDATA decoded) sends marker positions and
waits for the deformed surface. Printed side by side:

- round trip, POINT in -> POLYDATA TissueSurface out (p50 / p99 / max over N requests);
- the same with 5 TRANSFORM messages in, with the full field, and for a 5-member ensemble
  (surface + uncertainty);
- where the time goes: model evaluation, server-side handling of one request, and packing
  the reply with pyigtl.PolyDataMessage versus the pre-packed template;
- a fixed numpy kernel of similar size, whose p99 shows how much of the tail comes from the
  machine (other processes, scheduling) rather than from the server.

A model that reads a tracked instrument (``--model`` of the embedded preset: the retractor)
gets one TRANSFORM per instrument before each POINT (tip on the reference surface, pushing
along the tool's +z), as navigation streams them: the round trip is then POINT + TRANSFORM in,
POLYDATA out (target p99 < 3 ms), and the model's bounds and alarm are computed every frame.

Where g++ and the official OpenIGTLink C++ library (Debian libopenigtlink-dev) are installed,
the first round trip is also timed with the official client (tests/igtl_client, ``--latency``
mode: the same TRANSFORM and POINT per frame, the POLYDATA unpacked with the library's CRC
check, timed with std::chrono in the client), and the target line reads that client's p99.

With ``--interval S`` the first round trip is also timed paced, S seconds between a reply and the
next frame (a tracker streaming at 1 / S Hz), by the Python client and by the official one (a
second target line), beside a fixed numpy kernel served over the same kind of socket back to
back and paced: the machine's share of the paced latency.

Usage: python benchmarks/igtl_latency.py [--requests 2000] [--model FOLDER] [--interval 0.02]
"""

from __future__ import annotations

import argparse
import itertools
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyigtl

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the official client's build
import official_client  # noqa: E402

from tissuecast.mesh.phantom import phantom  # noqa: E402
from tissuecast.serve import IGTLClient, SurfacePredictor
from tissuecast.serve.session import ClientSession
from tissuecast.serve.synthetic import synthetic_model
from tissuecast.surrogate import DeformationModel


def per_call(fn, n: int, pause: float = 0.0) -> np.ndarray:
    """Seconds per call of fn(), n calls after 20 warm-up calls, each after ``pause`` seconds idle."""
    for _ in range(20):
        fn()
    out = np.empty(n)
    for i in range(n):
        if pause:
            time.sleep(pause)
        t = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t
    return out


def until_first_reply(session, messages, sent_at: list, n: int) -> np.ndarray:
    """Seconds from feeding a message to the session's first reply (the mesh), n messages after
    20 warm-up ones; ``sent_at`` is the list the session's emit appends its times to."""
    out = np.empty(n + 20)
    for i in range(n + 20):
        sent_at.clear()
        t = time.perf_counter()
        session.feed(next(messages))
        out[i] = sent_at[0] - t
    return out[20:]


def row(name: str, seconds: np.ndarray) -> str:
    us = seconds * 1e6
    return f"{name:<52s} {np.percentile(us, 50):9.1f} {np.percentile(us, 99):9.1f} {us.max():9.1f}"


def start_server(folder: Path, *extra: str) -> tuple[subprocess.Popen, int]:
    cmd = [sys.executable, "-c", "import sys; from tissuecast.cli.main import main; sys.exit(main())",
           "-q", "serve", str(folder), "--port", "0", *extra]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    line = proc.stdout.readline()  # "serving FOLDER on HOST:PORT (OpenIGTLink)"
    if " on " not in line:
        proc.kill()
        raise RuntimeError(f"server did not start: {line!r}")
    return proc, int(line.split(" on ")[1].split()[0].rsplit(":", 1)[1])


def round_trips(port: int, positions: np.ndarray, n: int, mode: str, tools: dict | None = None,
                pause: float = 0.0) -> np.ndarray:
    """Seconds per request; ``tools``: {device: packed TRANSFORM} sent before each request;
    ``pause``: seconds between a reply and the next request (0: back to back)."""
    rng = np.random.default_rng(0)
    with IGTLClient("127.0.0.1", port) as client:
        def once():
            p = positions + rng.normal(0.0, 0.5, positions.shape)
            for packed in (tools or {}).values():
                client.send(packed)
            if mode == "transform":
                client.send_transforms(p)
            else:
                client.send_positions(p)
            reply = client.receive()
            while reply.header.message_type == "STATUS":  # an alarm or an instrument's STATUS of the last frame
                reply = client.receive()
            if mode == "field":
                reply = client.receive()
            assert reply.polydata is not None, reply.text
        return per_call(once, n, pause)


def instrument_transforms(model, devices) -> dict:
    """{device: packed TRANSFORM} of each instrument device the model reads (``devices``,
    :attr:`SurfacePredictor.instrument_devices`), each the pose :func:`tool_pose`."""
    if not devices:
        return {}
    tool = tool_pose(model)
    return {device: pyigtl.TransformMessage(tool, device_name=device).pack() for device in devices}


def tool_pose(model) -> np.ndarray:
    """(4, 4) tool pose in the model frame: the tip on the surface vertex nearest the
    markers' centroid, 1 mm out along the outward axis from the body's centre, the tool's +z
    pushing in."""
    pts = model.mesh.points
    surface = pts[model.mesh.surface_vertices]
    tip = surface[np.argmin(np.linalg.norm(surface - model.reference_marker_positions.mean(axis=0), axis=1))]
    out = tip - pts.mean(axis=0)
    out /= np.linalg.norm(out)
    z = -out
    x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    tool = np.eye(4)
    tool[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    tool[:3, 3] = tip + out
    return tool


#: Bytes of one request to the fixed kernel's server.
REQUEST_BYTES = 200


def _kernel_server(port_queue) -> None:
    """Answer each request with a 28 kB reply after six (2 x 120) @ (120 x 3500) products over
    two fixed float64 matrices (a 6.7 MB footprint, about a served model's, read three times).
    Each request is the client's REQUEST_BYTES, read in full."""
    import socket

    with socket.create_server(("127.0.0.1", 0)) as listener:
        port_queue.put(listener.getsockname()[1])
        conn, _ = listener.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        mats = [np.random.default_rng(k).random((120, 3500)) for k in range(2)]
        h = np.ones((2, 120))
        reply = bytes(28000)
        while True:
            got = 0
            while got < REQUEST_BYTES:
                part = conn.recv(REQUEST_BYTES - got)
                if not part:
                    return
                got += len(part)
            for _ in range(3):
                for m in mats:
                    h @ m
            conn.sendall(reply)


def kernel_round_trips(n: int, pause: float) -> np.ndarray:
    """Seconds per round trip to :func:`_kernel_server` in another process (the machine's
    share of a paced round trip: sockets, wake-ups and caches gone cold between frames)."""
    import multiprocessing
    import socket

    ctx = multiprocessing.get_context("spawn")
    ports = ctx.Queue()
    proc = ctx.Process(target=_kernel_server, args=(ports,), daemon=True)
    proc.start()
    try:
        with socket.create_connection(("127.0.0.1", ports.get(timeout=60))) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

            def once():
                sock.sendall(b"x" * REQUEST_BYTES)
                got = 0
                while got < 28000:
                    got += len(sock.recv(65536))
            return per_call(once, n, pause)
    finally:
        proc.join(10)
        proc.kill()


def build_cpp_client(folder: Path) -> Path | None:
    """The official-library client compiled into ``folder``, or None (with the reason printed)
    where g++ or libopenigtlink-dev is missing."""
    missing = official_client.missing()
    if missing:
        print(f"official C++ client: not built ({missing})")
        return None
    return official_client.build(folder)


def cpp_round_trips(binary: Path, port: int, positions: np.ndarray, n: int, device: str | None,
                    pose: np.ndarray | None, pause: float = 0.0) -> np.ndarray:
    """Seconds per frame measured by the official client: TRANSFORM ``device`` (``pose``; none
    when ``device`` is None) and POINT in, POLYDATA out and unpacked; ``pause`` seconds between
    a reply and the next frame (0: back to back)."""
    pose = np.eye(4) if pose is None else pose
    args = [str(binary), "127.0.0.1", str(port), "--latency", str(n), device or "-", repr(pause * 1e3)]
    args += [repr(float(v)) for v in pose.ravel()] + [repr(float(v)) for v in np.asarray(positions).ravel()]
    done = subprocess.run(args, capture_output=True, text=True, timeout=max(120, n * (1 + pause)))
    if done.returncode != 0:
        raise RuntimeError(f"the official client failed ({done.returncode}): {done.stderr.strip()}")
    micros = [int(line.split()[1]) for line in done.stdout.splitlines() if line.startswith("R ")]
    return np.asarray(micros, dtype=np.float64) * 1e-6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--model", help="saved DeformationModel folder (default: a synthetic phantom model)")
    parser.add_argument("--interval", type=float, default=0.0,
                        help="also time the first round trip paced as a tracker streams: this many seconds between a "
                             "reply and the next frame (e.g. 0.02 for 50 Hz), beside a fixed kernel served alike")
    args = parser.parse_args()
    n = args.requests
    mesh = phantom()
    with tempfile.TemporaryDirectory() as tmp:
        if args.model:
            folder, model = Path(args.model), DeformationModel.load(args.model)
            ensemble = None
        else:
            t = time.perf_counter()
            model = synthetic_model(mesh, n_samples=300, n_components=27, hidden=(128, 64), epochs=30)
            ensemble = synthetic_model(mesh, n_samples=300, n_components=27, hidden=(128, 64), epochs=30, ensemble=5)
            print(f"fitted synthetic phantom models in {time.perf_counter() - t:.1f} s")
            folder = Path(tmp) / "model"
            model.save(folder)
            ensemble.save(Path(tmp) / "ensemble")
        print(f"mesh: {mesh.n_vertices} vertices, surface {len(mesh.surface_vertices)} vertices / "
              f"{len(mesh.surface_triangles)} triangles; {model!r}")
        positions = model.reference_marker_positions
        predictor = SurfacePredictor(model)
        prediction = predictor.predict(positions + 1.0, 0.0)
        sent_at: list[float] = []  # when the session handed each reply to the socket
        session = ClientSession(predictor, lambda data: sent_at.append(time.perf_counter()))
        jitter = np.random.default_rng(1)  # every frame's markers differ, as tracked ones do
        point_messages = itertools.cycle([pyigtl.PointMessage(positions + jitter.normal(0.0, 0.5, positions.shape),
                                                              device_name="Markers").pack() for _ in range(256)])
        tris = np.hstack([np.full((len(mesh.surface_triangles), 1), 3), np.searchsorted(
            predictor.surface_ids, mesh.surface_triangles)]).ravel()

        def pyigtl_pack():
            pts = (predictor.surface_reference + prediction.displacement[predictor.surface_ids]).astype(np.float32)
            return pyigtl.PolyDataMessage(points=pts, polygons=tris, device_name="TissueSurface").pack()

        print(f"\n{'microseconds':<52s} {'p50':>9s} {'p99':>9s} {'max':>9s}")
        W = np.random.default_rng(0).random((64, 3 * mesh.n_vertices))
        h = np.random.default_rng(1).random((1, 64))
        print(row("machine jitter floor: one fixed (1x64)@(64x3n) matmul", per_call(lambda: h @ W, n)))
        print(row("model.predict_from_positions", per_call(lambda: model.predict_from_positions(positions + 1.0), n)))
        tools = instrument_transforms(model, predictor.instrument_devices)
        for packed in tools.values():
            session.feed(packed)
        print(row("server work per POINT request (in-process)", per_call(lambda: session.feed(next(point_messages)), n)))
        print(row("  ... until the mesh is handed to the socket", until_first_reply(session, point_messages, sent_at, n)))
        packed = per_call(lambda: predictor.surface_message(prediction), n)
        naive = per_call(pyigtl_pack, n)
        print(row("pack surface: pre-packed template + segment CRC", packed))
        print(row("pack surface: pyigtl.PolyDataMessage.pack()", naive))
        print(f"{'  -> packing speed-up (p50)':<52s} {np.median(naive) / np.median(packed):9.1f}x")
        runs = [("round trip POINT -> TissueSurface", folder, (), "point"),
                ("round trip 5 TRANSFORM -> TissueSurface", folder, (), "transform"),
                ("round trip POINT -> TissueSurface + TissueField", folder, ("--full-field",), "field")]
        if ensemble is not None:
            runs.append(("round trip POINT -> surface + uncertainty (5 nets)", Path(tmp) / "ensemble", (), "point"))
        results = {}
        binary = build_cpp_client(Path(tmp))
        device = next(iter(tools), None)
        official = "round trip POINT -> TissueSurface, C++ client"
        official_paced = f"{official}, paced"
        between = f"paced, {args.interval * 1e3:g} ms between frames"
        for name, path, extra, mode in runs:
            proc, port = start_server(path, *extra)
            try:
                results[name] = round_trips(port, positions, n, mode, tools)
                print(row(name, results[name]))
                if args.interval and name == runs[0][0]:
                    paced = round_trips(port, positions, max(100, n // 4), mode, tools, args.interval)
                    print(row(f"  ... {between}", paced))
                if binary is not None and name == runs[0][0]:
                    pose = tool_pose(model) if device else None
                    results[official] = cpp_round_trips(binary, port, positions, n, device, pose)
                    print(row(official, results[official]))
                    if args.interval:
                        results[official_paced] = cpp_round_trips(binary, port, positions, n, device, pose,
                                                                  args.interval)
                        print(row(f"  ... {between}", results[official_paced]))
            finally:
                proc.terminate()
                proc.wait(10)
        if args.interval:
            for pause in (0.0, args.interval):
                print(row(f"fixed kernel server (6.7 MB footprint), pause {pause * 1e3:g} ms",
                          kernel_round_trips(max(100, n // 4), pause)))
        which = official if official in results else runs[0][0]
        what, target = ("POINT + TRANSFORM", 3.0) if tools else ("POINT", 1.0)
        client = "the official C++ client" if which == official else "the Python client"
        print()
        for key, how in ((which, "back to back"), (official_paced, between)):
            if key in results:
                p99 = np.percentile(results[key], 99) * 1e3
                print(f"{what} -> TissueSurface over {n} requests with {client}, {how}: p99 = {p99:.3f} ms "
                      f"({'meets' if p99 < target else 'MISSES'} the {target:g} ms target on this machine)")


if __name__ == "__main__":
    main()
