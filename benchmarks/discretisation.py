"""How far a data set's "truth" is from the mesh-converged answer: its discretisation error.

For a store (or a config, whose samples are then drawn without a store) and its first N test-1
samples, solves each sample again (:mod:`tissuecast.scenario.refined`) on

* the same mesh with quadratic elements (when the store's elements are linear), and
* the uniformly refined mesh (each tetrahedron into eight) with quadratic elements: the
  reference (``--reference refined``, the default),

reads every answer on the store's vertices and prints, per variant, the sample's largest
vertex error against the reference as a share of its peak displacement (median, p95, the
share of samples within 2 %), the 95th-percentile vertex error and the mean vertex error, and
where the largest errors sit (distance to the attached region and to the instrument's
contact). The refined solves start from the store's answer and are slow (minutes each on a
2-core machine for the phantom); the answers are cached in ``--cache``. ``--reference p2``
takes quadratic elements on the store's own mesh as the reference instead (no refined solve:
the element order's share of the error alone, a lower bound of the whole).

With ``--model LABEL=DIR`` (repeatable) every model is also evaluated on the same samples
twice, against the store's fields (the simulator it was trained on) and against the
reference's (the same loads, discretised better), with rigid registration and ridge from the
same markers: mean Offset_max and Offset_mean, TRE and the share of the targets' displacement
corrected (:func:`tissuecast.evaluate.mismatch.evaluate_on_set`).

Usage::

    python benchmarks/discretisation.py STORE [--samples 8] [--cache DIR] [--reference refined|p2]
        [--model LABEL=DIR ...]
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


def _answers(ds, k: int, scenario, refined, cache: Path, reference: str) -> dict:
    """``{"data", "p2", "reference"}`` vertex fields (n, 3) mm of sample ``k`` ("p2" only for a
    linear store; "reference" is "p2" with ``reference = "p2"``) and ``"contact"``, the
    instrument's contact vertex (None without an indentation)."""
    from tissuecast.scenario import restore_scenario
    from tissuecast.scenario.refined import refined_sample

    cfg = ds.config
    n = ds.mesh.n_vertices
    out = {"data": np.asarray(ds.displacements[k], dtype=np.float64)}
    x = scenario.sample(int(ds.seed[k]), float(ds.alpha[k]))
    out["contact"] = None if x.draw.indentation is None else int(x.draw.indentation.centre)
    p2_cfg = dataclasses.replace(cfg.solver, order=2)
    p2_path, ref_path = cache / f"sample_{k:05d}.p2.npy", cache / f"sample_{k:05d}.reference.npy"
    earlier = cache / f"sample_{k:05d}.npz"  # earlier versions kept both answers in one file
    if earlier.is_file():
        saved = np.load(earlier)
        for key, path in (("p2", p2_path), ("reference", ref_path)):
            if key in saved.files and not path.is_file():
                np.save(path, saved[key])
    if cfg.solver.order == 1:
        if not p2_path.is_file():
            from tissuecast.config import with_overrides

            cfg2 = with_overrides(cfg, solver={"order": 2})
            sc2 = restore_scenario(ds.mesh, cfg2, ds.scenario_arrays, ds.basis)
            x2 = sc2.sample(int(ds.seed[k]), float(ds.alpha[k]))
            problem = sc2.problem()
            changes = {key: v for key, v in zip(("materials", "springs"), x2.solver_parameters) if v is not None}
            np.save(p2_path, _solve(dataclasses.replace(problem, **changes) if changes else problem, p2_cfg,
                                    x2.surface, x2.solve_keywords(), guess=out["data"]))
        out["p2"] = np.load(p2_path)
    if reference == "p2":
        out["reference"] = out["p2"] if "p2" in out else out["data"]
        return out
    if not ref_path.is_file():
        fine = refined_sample(scenario, cfg, refined, x)  # the sample's own parameters, on the refined mesh
        np.save(ref_path, _solve(fine.problem, p2_cfg, fine.surface, fine.keywords,
                                 guess=refined.from_coarse(out["data"]))[:n])
    out["reference"] = np.load(ref_path)
    return out


def _models_against(ds, kept: list, fields: dict, specs: list) -> None:
    """Print every model's figures on the store's fields and on the reference's (same samples)."""
    from tissuecast.evaluate.mismatch import ArraySet, evaluate_on_set
    from tissuecast.surrogate import DeformationModel

    print(f"\nmodels on the same {len(kept)} samples (mean Offset_max / Offset_mean, mm; TRE mm, share corrected; "
          f"the 90 % bounds' coverage and the alarm's rate with a trust layer):")
    print("model          truth       MLP              rigid   ridge   MLP TRE        rigid corrected  coverage  alarm")
    for spec in specs:
        label, _, folder = spec.partition("=")
        model = DeformationModel.load(folder)
        for truth in ("data", "reference"):
            row = evaluate_on_set(model, ArraySet.of_samples(ds, kept, fields[truth]), None)
            print(f"{label:<14} {truth:<11} {row['mlp_offset_max']:6.2f} / {row['mlp_offset_mean']:5.3f}   "
                  f"{row['rigid_offset_max']:6.2f}  {row['ridge_offset_max']:6.2f}  "
                  f"{row.get('mlp_tre_mean', float('nan')):5.2f} ({100 * row.get('mlp_corrected', float('nan')):3.0f} %)   "
                  f"{100 * row.get('rigid_corrected', float('nan')):3.0f} %            "
                  f"{100 * row.get('coverage_90', float('nan')):5.1f} %  {100 * row.get('alarm_rate', float('nan')):4.0f} %",
                  flush=True)


def main(argv=None) -> int:
    from tissuecast.dataset import open_dataset
    from tissuecast.errors import ConvergenceError
    from tissuecast.mesh.refine import refine_uniformly
    from tissuecast.scenario import restore_scenario

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--cache", default="")
    ap.add_argument("--reference", choices=("refined", "p2"), default="refined",
                    help="refined: P2 on the uniformly refined mesh; p2: P2 on the store's mesh (no refined solve)")
    ap.add_argument("--model", action="append", default=[], metavar="LABEL=DIR",
                    help="evaluate a model against the store's fields and the reference's")
    args = ap.parse_args(argv)
    ds = open_dataset(args.store)
    if args.reference == "p2" and ds.config.solver.order == 2:
        raise SystemExit("the store's elements are quadratic already: --reference p2 would compare it with itself; "
                         "use --reference refined")
    cache = Path(args.cache or Path(args.store).with_suffix(".discretisation"))
    cache.mkdir(parents=True, exist_ok=True)
    scenario = restore_scenario(ds.mesh, ds.config, ds.scenario_arrays, ds.basis)
    refined = refine_uniformly(ds.mesh) if args.reference == "refined" else None
    rows: dict[str, list] = {}
    t0 = time.perf_counter()
    attached = ds.mesh.points[np.asarray(ds.scenario_arrays.get("attached", []), dtype=np.int64)]
    kept, fields = [], {"data": [], "reference": []}
    for k in ds.select("test1", status="done")[: args.samples]:
        try:
            a = _answers(ds, int(k), scenario, refined, cache, args.reference)
        except ConvergenceError as exc:
            print(f"sample {int(k)}: a solve did not converge ({exc}); left out", flush=True)
            continue
        kept.append(int(k))
        for key in fields:
            fields[key].append(a[key])
        ref = a["reference"]
        peak = float(np.linalg.norm(ref, axis=1).max())
        for name in ("data", "p2"):
            if name in a and not (args.reference == "p2" and name == "p2"):
                e = np.linalg.norm(a[name] - ref, axis=1)
                rows.setdefault(name, []).append((e.max() / peak, np.percentile(e, 95), e.mean(), peak))
        worst = ds.mesh.points[int(np.argmax(np.linalg.norm(a["data"] - ref, axis=1)))]
        to_attached = np.linalg.norm(attached - worst, axis=1).min() if len(attached) else float("nan")
        to_contact = float("nan") if a["contact"] is None else np.linalg.norm(ds.mesh.points[a["contact"]] - worst)
        print(f"sample {int(k)}: peak {peak:.2f} mm, data's largest error {100 * rows['data'][-1][0]:.1f} % of it, "
              f"{to_attached:.1f} mm from the attached region and {to_contact:.1f} mm from the instrument's contact "
              f"({time.perf_counter() - t0:.0f} s so far)", flush=True)
    order = "P1" if ds.config.solver.order == 1 else "P2"
    labels = {"data": f"the data set ({order}, this mesh)", "p2": "P2, this mesh"}
    where = "the refined mesh" if args.reference == "refined" else "this mesh"
    print(f"\nagainst P2 on {where}, {len(rows['data'])} test-1 samples:")
    print("variant                      max error / peak: median  p95    within 2 %   p95 vertex error  mean error")
    for name, r in rows.items():
        r = np.asarray(r)
        print(f"{labels[name]:<28} {100 * np.median(r[:, 0]):6.1f} %  {100 * np.percentile(r[:, 0], 95):6.1f} %  "
              f"{100 * np.mean(r[:, 0] <= 0.02):6.0f} %      {np.median(r[:, 1]):.3f} mm         "
              f"{np.median(r[:, 2]):.3f} mm")
    if args.model and kept:
        _models_against(ds, kept, fields, args.model)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
