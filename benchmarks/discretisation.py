"""How far a data set's "truth" is from the mesh-converged answer: its discretisation error.

For a store (or a config, whose samples are then drawn without a store) and its first N test-1
samples, solves each sample again (:mod:`tissuecast.scenario.refined`) on

* the same mesh with quadratic elements (when the store's elements are linear), and
* the uniformly refined mesh (each tetrahedron into eight) with quadratic elements: the
  reference,

reads every answer on the store's vertices and prints, per variant, the sample's largest
vertex error against the reference as a share of its peak displacement (median, p95, the
share of samples within 2 %), the 95th-percentile vertex error and the mean vertex error, and
where the largest errors sit (distance to the attached region and to the instrument's
contact). The refined solves start from the store's answer and are slow (minutes each on a
2-core machine for the phantom); the answers are cached in ``--cache``.

Usage::

    python benchmarks/discretisation.py STORE [--samples 8] [--cache DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np


def _solve(problem, solver_cfg, surface, keywords, guess=None):
    from tissuecast.fem import Solver

    kw = {} if guess is None else {"initial_guess": guess}
    return Solver(problem, solver_cfg).solve(surface, **keywords, **kw).displacement


def _answers(ds, k: int, scenario, refined, cache: Path) -> dict:
    """``{"data", "p2", "reference"}`` vertex fields (n, 3) mm of sample ``k``."""
    from tissuecast.scenario import restore_scenario
    from tissuecast.scenario.refined import refined_sample

    cfg = ds.config
    n = ds.mesh.n_vertices
    out = {"data": np.asarray(ds.displacements[k], dtype=np.float64)}
    x = scenario.sample(int(ds.seed[k]), float(ds.alpha[k]))
    p2_cfg = dataclasses.replace(cfg.solver, order=2)
    path = cache / f"sample_{k:05d}.npz"
    if path.is_file():
        saved = np.load(path)
        return {**out, **{key: saved[key] for key in saved.files}}
    if cfg.solver.order == 1:
        from tissuecast.config import with_overrides

        cfg2 = with_overrides(cfg, solver={"order": 2})
        sc2 = restore_scenario(ds.mesh, cfg2, ds.scenario_arrays, ds.basis)
        x2 = sc2.sample(int(ds.seed[k]), float(ds.alpha[k]))
        problem = sc2.problem()
        changes = {key: v for key, v in zip(("materials", "springs"), x2.solver_parameters) if v is not None}
        out["p2"] = _solve(dataclasses.replace(problem, **changes) if changes else problem, p2_cfg, x2.surface,
                           x2.solve_keywords(), guess=out["data"])
    fine = refined_sample(scenario, cfg, refined, x)  # the sample's own parameters, on the refined mesh
    out["reference"] = _solve(fine.problem, p2_cfg, fine.surface, fine.keywords,
                              guess=refined.from_coarse(out["data"]))[:n]
    np.savez(path, **{key: v for key, v in out.items() if key != "data"})
    return out


def main(argv=None) -> int:
    from tissuecast.dataset import open_dataset
    from tissuecast.mesh.refine import refine_uniformly
    from tissuecast.scenario import restore_scenario

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--cache", default="")
    args = ap.parse_args(argv)
    ds = open_dataset(args.store)
    cache = Path(args.cache or Path(args.store).with_suffix(".discretisation"))
    cache.mkdir(parents=True, exist_ok=True)
    scenario = restore_scenario(ds.mesh, ds.config, ds.scenario_arrays, ds.basis)
    refined = refine_uniformly(ds.mesh)
    rows: dict[str, list] = {}
    t0 = time.perf_counter()
    for k in ds.select("test1", status="done")[: args.samples]:
        a = _answers(ds, int(k), scenario, refined, cache)
        ref = a["reference"]
        peak = float(np.linalg.norm(ref, axis=1).max())
        for name in ("data", "p2"):
            if name in a:
                e = np.linalg.norm(a[name] - ref, axis=1)
                rows.setdefault(name, []).append((e.max() / peak, np.percentile(e, 95), e.mean(), peak))
        print(f"sample {int(k)}: peak {peak:.2f} mm, data's largest error {100 * rows['data'][-1][0]:.1f} % of it "
              f"({time.perf_counter() - t0:.0f} s so far)", flush=True)
    order = "P1" if ds.config.solver.order == 1 else "P2"
    labels = {"data": f"the data set ({order}, this mesh)", "p2": "P2, this mesh"}
    print(f"\nagainst P2 on the refined mesh, {len(rows['data'])} test-1 samples:")
    print("variant                      max error / peak: median  p95    within 2 %   p95 vertex error  mean error")
    for name, r in rows.items():
        r = np.asarray(r)
        print(f"{labels[name]:<28} {100 * np.median(r[:, 0]):6.1f} %  {100 * np.percentile(r[:, 0], 95):6.1f} %  "
              f"{100 * np.mean(r[:, 0] <= 0.02):6.0f} %      {np.median(r[:, 1]):.3f} mm         "
              f"{np.median(r[:, 2]):.3f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
