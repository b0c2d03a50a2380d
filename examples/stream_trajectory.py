"""Stream a recorded marker trajectory to `tissuecast serve` and save the meshes for ParaView.

Each frame of the trajectory (CSV: ``time_s, m0_x, m0_y, m0_z, m1_x, ...`` in s and mm, one
row per frame, markers in the model's order and coordinate frame) is sent as one OpenIGTLink
POINT message; the deformed surface that comes back (POLYDATA ``TissueSurface``) is written
as ``surface_0000.vtu``, ``surface_0001.vtu``, ... with a ``surface.pvd`` collection that
ParaView opens as a time series (uncertainty, if the model is an ensemble, as point data).

Usage::

    # against a running server (`tissuecast serve MODEL`), with a recorded trajectory
    python examples/stream_trajectory.py --port 18944 --trajectory markers.csv --out frames/
    # self-contained: serve MODEL in-process and make a sample trajectory from its markers
    python examples/stream_trajectory.py --model MODEL --out frames/
    # no model at hand: a quickly fitted synthetic model on the phantom (plumbing demo only)
    python examples/stream_trajectory.py --out frames/
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

from tissuecast.serve import IGTLClient, IGTLServer


def sample_trajectory(reference: np.ndarray, n_frames: int = 60, rate: float = 30.0, amplitude: float = 3.0,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth synthetic marker motion: each coordinate oscillates about its reference position.

    Args:
        reference: (n_d, 3) float, mm, reference marker positions.
        n_frames: F, number of frames; rate: frames per second; amplitude: mm.

    Returns:
        (times (F,) s, positions (F, n_d, 3) mm).
    """
    rng = np.random.default_rng(seed)
    times = np.arange(n_frames) / rate
    freq = rng.uniform(0.2, 0.6, size=reference.shape)  # Hz
    phase = rng.uniform(0, 2 * np.pi, size=reference.shape)
    sway = amplitude * np.sin(2 * np.pi * freq * times[:, None, None] + phase) * np.minimum(times, 1.0)[:, None, None]
    return times, reference[None] + sway


def write_trajectory(path: Path, times: np.ndarray, positions: np.ndarray) -> None:
    """Write a trajectory CSV (time_s, m0_x, m0_y, m0_z, ...)."""
    n_d = positions.shape[1]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["time_s"] + [f"m{i}_{a}" for i in range(n_d) for a in "xyz"])
        for t, p in zip(times, positions):
            writer.writerow([f"{t:.6f}"] + [f"{v:.6f}" for v in p.ravel()])


def read_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a trajectory CSV -> (times (F,) s, positions (F, n_d, 3) mm)."""
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if table.shape[1] < 4 or (table.shape[1] - 1) % 3:
        raise SystemExit(f"{path}: expected columns time_s + 3 per marker, got {table.shape[1]} columns")
    return table[:, 0], table[:, 1:].reshape(len(table), -1, 3)


def write_pvd(path: Path, times: np.ndarray, files: list[Path]) -> None:
    """A ParaView collection listing one VTU file per time step."""
    rows = "\n".join(f'    <DataSet timestep="{t:.6f}" part="0" file={quoteattr(f.name)}/>' for t, f in zip(times, files))
    path.write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
                    f"{rows}\n  </Collection>\n</VTKFile>\n")


def stream(host: str, port: int, times: np.ndarray, positions: np.ndarray, out: Path) -> list[Path]:
    """Send every frame, wait for its surface, write it as VTU; returns the VTU paths (+ .pvd)."""
    out.mkdir(parents=True, exist_ok=True)
    files = []
    with IGTLClient(host, port) as client:
        for index, (t, frame) in enumerate(zip(times, positions)):
            client.send_positions(frame, timestamp=float(t))
            reply = client.receive()
            if reply.is_error:
                raise SystemExit(f"frame {index}: server error: {reply.text}")
            poly = reply.polydata
            path = out / f"surface_{index:04d}.vtu"
            meshio.write_points_cells(path, poly.points.astype(np.float64), [("triangle", poly.triangles())],
                                      point_data={k: v for k, v in poly.point_data.items()})
            files.append(path)
    write_pvd(out / "surface.pvd", times, files)
    return files


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", help="saved DeformationModel folder (default: synthetic phantom model)")
    parser.add_argument("--trajectory", help="CSV trajectory; default: a sample written to OUT/trajectory.csv")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, help="port of a running `tissuecast serve`; default: serve in-process")
    parser.add_argument("--frames", type=int, default=60, help="frames of the sample trajectory")
    parser.add_argument("--out", default="stream_frames", help="output folder")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = None
    if args.model:
        from tissuecast.surrogate import DeformationModel

        model = DeformationModel.load(args.model)
    elif args.port is None or args.trajectory is None:
        from tissuecast.mesh.phantom import phantom
        from tissuecast.serve.synthetic import synthetic_model

        print("no --model: fitting a small synthetic model on the phantom (plumbing demo, not tissue mechanics)")
        model = synthetic_model(phantom(), n_samples=100, epochs=20)
    if args.trajectory:
        times, positions = read_trajectory(Path(args.trajectory))
    else:
        times, positions = sample_trajectory(model.reference_marker_positions, args.frames)
        write_trajectory(out / "trajectory.csv", times, positions)
        print(f"wrote sample trajectory {out / 'trajectory.csv'} ({len(times)} frames)")
    if args.port is None:
        with IGTLServer(model, "127.0.0.1", 0) as server:
            files = stream(*server.address, times, positions, out)
    else:
        files = stream(args.host, args.port, times, positions, out)
    print(f"wrote {len(files)} surfaces and {out / 'surface.pvd'} (open it in ParaView)")
    return files


if __name__ == "__main__":
    main()
