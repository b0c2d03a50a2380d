"""A preset from mesh to evaluated model, timed end to end, with the peak memory of its processes.

Runs ``tissuecast run CONFIG`` (default: the packaged paper preset) in a fresh folder, as a
user would, optionally on the phantom re-meshed at a scale of its element sizes
(``--phantom-scale 0.66``: ~3500 vertices; 0.44: ~11 000), and prints

* the wall time from mesh to evaluated model, next to ``--target-minutes``,
* the phases the run reports (simulate / train / evaluate) and the data set's per-sample
  worker time, Newton iterations and failures (``tissuecast dataset info``),
* the accuracy table's test-1 rows (MLP, rigid registration from the same markers, ridge,
  PCA floor; the non-rigid part of the deformation),
* the peak resident memory of all the run's processes together and of the largest one,
  sampled every ``--every`` seconds from ``/proc`` (Linux).

``--stop-after S`` stops the run after S seconds (the store resumes with the same command)
and reports the samples done by then, for meshes whose paper-size set takes hours.

Usage::

    python benchmarks/preset_run.py [--config paper] [--phantom-scale 0.66] [--target-minutes 30]

Figures of this machine (idle, 2 cores): docs/scaling.md. A run beside other jobs is slower;
say so when quoting it.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _tree_rss(root: int) -> tuple[float, float]:
    """(sum, largest) resident memory in MB of process ``root`` and its descendants (Linux)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, float] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            status = (d / "status").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(d.name))
        m = re.search(r"VmRSS:\s+(\d+) kB", status)
        rss[int(d.name)] = int(m.group(1)) / 1024.0 if m else 0.0
    todo, seen = [root], []
    while todo:
        pid = todo.pop()
        seen.append(pid)
        todo.extend(children.get(pid, []))
    values = [rss.get(p, 0.0) for p in seen]
    return sum(values), max(values, default=0.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="paper", help="a preset name or a TOML file (default: paper)")
    ap.add_argument("--phantom-scale", type=float, default=0.0,
                    help="re-mesh the phantom at this scale of its element sizes (0 = the shipped phantom)")
    ap.add_argument("--target-minutes", type=float, default=5.0, help="target printed next to the time (default 5)")
    ap.add_argument("--stop-after", type=float, default=0.0, help="stop the run after this many seconds (0 = never)")
    ap.add_argument("--every", type=float, default=2.0, help="memory sampling interval, s")
    ap.add_argument("--folder", default="", help="where to run (default: a new temporary folder)")
    args = ap.parse_args(argv)

    from tissuecast.cli.presets import preset_config
    from tissuecast.config import config_to_toml, load_config, with_overrides

    folder = Path(args.folder or tempfile.mkdtemp(prefix="tc-preset-"))
    folder.mkdir(parents=True, exist_ok=True)
    cfg = load_config(args.config) if args.config.endswith(".toml") else preset_config(args.config)
    if args.phantom_scale > 0:
        import meshio

        from tissuecast.mesh.shapes import phantom_mesh

        mesh = phantom_mesh(args.phantom_scale)
        meshio.write(folder / "mesh.vtu", meshio.Mesh(mesh.points, [("tetra", mesh.tets)]))
        cfg = with_overrides(cfg, mesh={"path": str(folder / "mesh.vtu")})
        print(f"phantom at {args.phantom_scale} of its sizes: {mesh.n_vertices} vertices, {len(mesh.tets)} tetrahedra")
    cfg = with_overrides(cfg, output=str(folder / "run"), dataset={"store": str(folder / "run" / "dataset.zarr")})
    (folder / "config.toml").write_text(config_to_toml(cfg))

    log = open(folder / "run.log", "w")
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "tissuecast.cli.main", "run", str(folder / "config.toml"),
                             "--no-progress"], stdout=log, stderr=subprocess.STDOUT, cwd=folder)
    peak_sum = peak_one = 0.0
    stopped = False
    while proc.poll() is None:
        total, one = _tree_rss(proc.pid)
        peak_sum, peak_one = max(peak_sum, total), max(peak_one, one)
        if args.stop_after and time.monotonic() - t0 > args.stop_after:
            proc.terminate()
            proc.wait()
            stopped = True
            break
        time.sleep(args.every)
    wall = time.monotonic() - t0
    log.close()
    text = (folder / "run.log").read_text()
    verdict = "" if stopped else ": met" if wall <= 60 * args.target_minutes else ": not met"
    what = "stopped after" if stopped else "mesh -> evaluated model in"
    print(f"\nconfig {args.config}: {what} {wall // 60:.0f} min {wall % 60:.0f} s (target {args.target_minutes:g} min"
          f"{verdict}); exit code {proc.returncode}; log {folder / 'run.log'}")
    print(f"peak resident memory: {peak_sum / 1024:.1f} GB all processes, {peak_one / 1024:.1f} GB the largest "
          f"(sampled every {args.every:g} s)")
    for line in text.splitlines():
        if line.startswith(("time:", "data set ", "quantity ", "test-1 mean Offset_max", "test-1 non-rigid part")):
            print(line)
    info = subprocess.run([sys.executable, "-m", "tissuecast.cli.main", "dataset", "info", str(folder / "run" / "dataset.zarr")],
                          capture_output=True, text=True)
    for line in info.stdout.splitlines():
        if line.startswith(("solver:", "reduced-model predictor:", "  from the prediction", "  total")):
            print(line)
    return 0 if (proc.returncode == 0 or stopped) else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
