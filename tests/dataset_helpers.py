"""Shared helpers of the data-set tests: a small mesh, configs, a fake solver.

Worker processes are spawned, so anything they import (the fake solver factory) must live in
an importable module: ``tests/conftest.py`` puts this folder on ``sys.path``, which spawned
children inherit.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from tissuecast.config import config_to_toml, with_overrides, Config
from tissuecast.errors import ConvergenceError

from mesh_factories import box_grid


def small_mesh_file(folder: Path) -> Path:
    """A 3 x 4 x 6-cell box (7.5 x 10 x 15 mm cells... 140 vertices, 432 tets) written as .vtu."""
    from tissuecast.mesh import write_mesh

    path = Path(folder) / "box.vtu"
    if not path.exists():
        write_mesh(path, box_grid(3, 4, 6, size=(7.0, 8.0, 10.0)))
    return path


def small_config(folder: Path, **dataset) -> Config:
    """A config for fast tests: the small box, P1 elements, few samples, fixed alpha."""
    ds = {"n_samples": 10, "n_test2": 3, "workers": 2, "alpha": 2.0, "calibration_samples": 2, "seed": 7}
    ds.update(dataset)
    return with_overrides(
        Config(),
        mesh={"path": str(small_mesh_file(folder))},
        markers={"start": 0, "min_distance": 5.0, "count": 4, "fixed_count": 3},
        solver={"order": 1},
        forces={"n_basis": 8, "betas": [0.0, 0.5, 1.0], "target_max_displacement": 10.0},
        dataset=ds,
    )


def tracked_retractor_config(folder: Path, uncertain: dict | None = None, **indentation) -> Config:
    """The embedded preset's kind on the small box (:data:`bench_helpers.SPRING_HELD`: attached
    bottom face, springs, gravity change) with a tracked retractor touching the tissue in 60 %
    of 30 samples (``indentation`` overrides its section); 14 markers and 4 LBO modes (12 load
    weights), so that the markers determine the loads; peaks of a few mm. ``uncertain``: a
    ``[scenario.uncertain]`` section (default none drawn)."""
    from bench_helpers import SPRING_HELD

    sc = {**SPRING_HELD, "indentation": {"enabled": True, "radius": 11.0, "depth": [0.5, 1.5], "slide": [0.0, 0.5],
                                         "probability": 0.6, **indentation},
          "instruments": [{"name": "retractor", "load": "indentation", "device": "RetractorToReference"}]}
    if uncertain:
        sc["uncertain"] = uncertain
    return with_overrides(small_config(folder), forces={"loading": "traction", "target_max_displacement": 4.0,
                                                        "n_basis": 4},
                          markers={"count": 14, "min_distance": 4.0}, scenario=sc, solver={"force_tolerance": 1e-10},
                          dataset={"n_samples": 30, "n_test2": 0, "alpha": 0.0, "calibration_samples": 2,
                                   "predictor_samples": 6})


def tracked_retractor_store(folder: Path, uncertain: dict | None = None):
    """``(config, store path, model folder)``: :func:`tracked_retractor_config`'s 30 samples
    (``uncertain`` drawn) simulated (none failed) and a small model trained on them, saved."""
    from tissuecast.dataset import open_dataset, simulate
    from tissuecast.surrogate import DeformationModel

    cfg = tracked_retractor_config(folder, uncertain)
    store = Path(folder) / "store.zarr"
    assert simulate(cfg, store, progress=False)["totals"]["failed"] == 0
    model = DeformationModel.from_dataset(open_dataset(store), cfg, epochs=20, patience=0, calibration_share=0.0,
                                          n_components=4)
    model.save(Path(folder) / "model")
    return cfg, store, Path(folder) / "model"


def write_config(cfg: Config, path: Path) -> Path:
    path = Path(path)
    path.write_text(config_to_toml(cfg, comments=False))
    return path


def worker_failing_solver_factory(scenario, cfg):
    """The fake solver, except in the first worker process to build it (the one that creates
    ``FAIL_MARKER`` in the mesh's folder): there it fails (a worker that cannot build its
    solver from the recipe while the others can)."""
    import multiprocessing
    import os

    if multiprocessing.parent_process() is not None:
        marker = Path(cfg.mesh.path).parent / FAIL_MARKER
        try:
            os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return fake_solver_factory(scenario, cfg)
        raise RuntimeError("this worker cannot build its solver")
    return fake_solver_factory(scenario, cfg)


FAIL_MARKER = "first-worker-fails"


def fake_solver_factory(scenario, cfg):
    """A deterministic stand-in solver: u = forces * 0.5 mm/N, failing when |f| > 1 N anywhere."""

    def make(solver_cfg):
        def solve(forces, initial_guess=None, time_limit=None):
            if np.abs(forces).max() > 1.0:
                raise ConvergenceError("increment too small at load fraction 0.4", 0.4)
            return SimpleNamespace(displacement=np.asarray(forces) * 0.5, increments=1, iterations=2, factorizations=2)

        return SimpleNamespace(solve=solve)

    return make


def _flagged_solver_factory(scenario, cfg, variable: str, act):
    """The fake solver, except that a solve while the file named by the environment ``variable``
    exists calls ``act(flag path)`` first (which removes the file: once per flag)."""
    import os

    fake = fake_solver_factory(scenario, cfg)

    def make(solver_cfg):
        inner = fake(solver_cfg)

        def solve(forces, initial_guess=None, time_limit=None):
            flag = os.environ.get(variable)
            if flag and os.path.exists(flag):
                act(flag)
            return inner.solve(forces, initial_guess)

        return SimpleNamespace(solve=solve)

    return make


def dying_solver_factory(scenario, cfg):
    """The fake solver, except that the worker process dies (os._exit) on its first solve
    while the file named by ``TISSUECAST_TEST_DIE`` exists (the file is removed first)."""
    import os

    def die(flag):
        os.remove(flag)
        os._exit(1)

    return _flagged_solver_factory(scenario, cfg, "TISSUECAST_TEST_DIE", die)


def half_sent_solver_factory(scenario, cfg):
    """The fake solver, except that on its first solve while the file named by
    ``TISSUECAST_TEST_HALF_SENT`` exists (the file is removed first) the worker writes the start
    of a result message into the pool's result pipe (a header promising 1 MB, then 64 bytes)
    and sleeps: the state a worker terminated while it sent its result leaves behind."""
    import os
    import struct
    import sys
    import time

    def half_send(flag):
        frame = sys._getframe()
        while frame.f_code.co_name != "_process_worker":  # concurrent.futures' worker loop
            frame = frame.f_back
        writer = frame.f_locals["result_queue"]._writer
        os.write(writer.fileno(), struct.pack("!i", 1 << 20) + bytes(64))
        os.remove(flag)
        time.sleep(600)

    return _flagged_solver_factory(scenario, cfg, "TISSUECAST_TEST_HALF_SENT", half_send)


#: The stalling solver's samples whose largest nodal force lies in this band (N) stall.
STALL_BAND = (0.6, 0.7)


def stalling_solver_factory(scenario, cfg):
    """The fake solver, except that samples whose largest force lies in ``STALL_BAND`` stall
    at every retry level: without a time limit they take 1.5 s and converge, with one they
    run to it and raise SolveTimeout (as the FEM solver does)."""
    import time

    from tissuecast.errors import SolveTimeout

    fake = fake_solver_factory(scenario, cfg)

    def make(solver_cfg):
        inner = fake(solver_cfg)

        def solve(forces, initial_guess=None, time_limit=None):
            if STALL_BAND[0] < np.abs(forces).max() <= STALL_BAND[1]:
                if time_limit is None:
                    time.sleep(1.5)
                else:
                    time.sleep(time_limit + 0.01)
                    raise SolveTimeout(f"stopped after {time_limit + 0.01:.1f} s, past its time limit", time_limit, time_limit)
            return inner.solve(forces, initial_guess)

        return SimpleNamespace(solve=solve)

    return make


def _fingerprint(forces) -> int:
    """A pseudo-random but deterministic number of a force field (picks the flaky samples)."""
    return int(np.abs(np.asarray(forces, dtype=np.float64)).sum() * 1e6)


def batch_failing_solver_factory(scenario, cfg):
    """The real FEM solver, except that in ``solve_batch`` every sample whose force field's
    fingerprint is a multiple of 4 fails (ConvergenceError at load fraction 0.5, the others
    solved by the real batch), and of those, the multiples of 3 fail every solve alone too
    (once they have failed in a batch of this process)."""
    from tissuecast.fem import Solver

    failed_in_batch: set = set()

    class FlakyBatches(Solver):
        def solve_batch(self, forces, initial_guesses=None, *, time_limit=None):
            forces = list(forces)
            guesses = [None] * len(forces) if initial_guesses is None else list(initial_guesses)
            flaky = [_fingerprint(f) % 4 == 0 for f in forces]
            kept = super().solve_batch([f for f, x in zip(forces, flaky) if not x],
                                       [g for g, x in zip(guesses, flaky) if not x], time_limit=time_limit)
            out = []
            for f, x in zip(forces, flaky):
                if x:
                    failed_in_batch.add(_fingerprint(f))
                    out.append(ConvergenceError("made to fail in a batch", 0.5))
                else:
                    out.append(kept.pop(0))
            return out

        def solve(self, forces, initial_guess=None, time_limit=None):
            fp = _fingerprint(forces)
            if fp in failed_in_batch and fp % 3 == 0:
                raise ConvergenceError("made to fail alone too", 0.25)
            return super().solve(forces, initial_guess=initial_guess, time_limit=time_limit)

    problem = scenario.problem()
    return lambda solver_cfg: FlakyBatches(problem, solver_cfg)


def store_arrays(path) -> dict:
    """Every array of a store as raw bytes, by path (``samples/seconds`` excluded: wall-clock)."""
    import zarr

    root = zarr.open_group(str(path), mode="r")
    out = {}
    for name, arr in root.members(max_depth=None):
        if isinstance(arr, zarr.Array) and name != "samples/seconds":
            a = arr[...]
            out[name] = (a.dtype.str, a.shape, a.tobytes())
    return out


def store_attrs(path) -> dict:
    import zarr

    attrs = dict(zarr.open_group(str(path), mode="r").attrs)
    attrs.pop("created")
    return attrs


def assert_same_store(a, b) -> None:
    """Two stores hold the same arrays bit for bit (``samples/seconds`` aside) and the same
    attributes (``created`` aside)."""
    arrays_a, arrays_b = store_arrays(a), store_arrays(b)
    assert arrays_a.keys() == arrays_b.keys()
    differ = [k for k in arrays_a if arrays_a[k] != arrays_b[k]]
    assert not differ, f"arrays differ: {differ}"
    assert store_attrs(a) == store_attrs(b)


def done_count(path) -> int:
    """Samples of a store (possibly being written) that are no longer pending; 0 before it exists."""
    import zarr

    try:
        return int((zarr.open_array(str(Path(path) / "samples" / "status"), mode="r")[:] > 0).sum())
    except Exception:  # not created yet
        return 0
