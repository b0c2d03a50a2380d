"""How far a data set's "truth" is from the mesh-converged answer: its discretisation error.

For a store (or a config, whose samples are then drawn without a store) and its first N test-1
samples, solves each sample again (:mod:`tissuecast.scenario.refined`) on

* the same mesh with quadratic elements (when the store's elements are linear), and
* the uniformly refined mesh (each tetrahedron into eight) with quadratic elements: the
  reference (``--reference refined``, the default),

reads every answer on the store's vertices and prints, per variant, the sample's largest
vertex error against the reference as a share of its peak displacement (median, p95, the
share of samples within 2 %), the 95th-percentile vertex error and the mean vertex error, the
same largest error once the best rigid motion between the two deformed bodies is taken out
(how much of the error is a swing of the whole body, which markers see, and the angle of
that swing), and where the largest errors sit (distance to the supports, the pins and the
attached region, and to the instrument's contact). The solves take the store's own path (from
zero along the load path, or from the store's answer when the store was solved from a guess;
:class:`~tissuecast.evaluate.mismatch.ReferenceSolver`) and are slow (minutes each on a 2-core
machine for the phantom); a solve past
``--time-limit`` is stopped and its sample left out; the answers are cached in ``--cache`` (with
the path they were solved along: answers of another path are moved to ``superseded/``).
``--reference p2``
takes quadratic elements on the store's own mesh as the reference instead (no refined solve:
the element order's share of the error alone, a lower bound of the whole).

With ``--model LABEL=DIR`` (repeatable) every model is also evaluated on the same samples
twice, against the store's fields (the simulator it was trained on) and against the
reference's (the same loads, discretised better), with rigid registration and ridge from the
same markers: mean Offset_max and Offset_mean, TRE and the share of the targets' displacement
corrected (:func:`tissuecast.evaluate.mismatch.evaluate_on_set`).

Usage::

    python benchmarks/discretisation.py STORE [--samples 8] [--cache DIR] [--reference refined|p2]
        [--model LABEL=DIR ...] [--time-limit 900]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def _answers(ds, k: int, solvers: dict, cache: Path, reference: str, time_limit=None) -> dict:
    """``{"data", "p2", "reference"}`` vertex fields (n, 3) mm of sample ``k`` ("p2" only for a
    linear store; "reference" is "p2" with ``reference = "p2"``) and ``"contact"``, the
    instrument's contact vertex (None without an indentation). ``solvers``: ``{"p2", "refined"}``
    :class:`~tissuecast.evaluate.mismatch.ReferenceSolver` (those needed)."""
    out = {"data": np.asarray(ds.displacements[k], dtype=np.float64)}
    scenario = next(iter(solvers.values())).scenario
    x = scenario.sample(int(ds.seed[k]), float(ds.alpha[k]))
    out["contact"] = None if x.draw.indentation is None else int(x.draw.indentation.centre)
    p2_path, ref_path = cache / f"sample_{k:05d}.p2.npy", cache / f"sample_{k:05d}.reference.npy"
    earlier = cache / f"sample_{k:05d}.npz"  # earlier versions kept both answers in one file
    if earlier.is_file():
        saved = np.load(earlier)
        for key, path in (("p2", p2_path), ("reference", ref_path)):
            if key in saved.files and not path.is_file():
                np.save(path, saved[key])
    if "p2" in solvers:
        if not p2_path.is_file():
            np.save(p2_path, solvers["p2"].solve(k, time_limit=time_limit))
        out["p2"] = np.load(p2_path)
    if reference == "p2":
        out["reference"] = out["p2"]
        return out
    if not ref_path.is_file():
        np.save(ref_path, solvers["refined"].solve(k, time_limit=time_limit))
    out["reference"] = np.load(ref_path)
    return out


def _after_rigid(points: np.ndarray, field: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """``(vertex errors (n,) mm, angle deg)``: ``field`` (n, 3) mm against ``ref`` once the rigid
    motion that best maps the reference's deformed body onto the field's is taken out."""
    from tissuecast.registration import fit_rigid

    t = fit_rigid(points + ref, points + field)
    angle = np.degrees(np.arccos(np.clip((np.trace(t.rotation) - 1.0) / 2.0, -1.0, 1.0)))
    return np.linalg.norm(points + field - t.apply(points + ref), axis=1), float(angle)


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
    from tissuecast.errors import ConvergenceError, SolveTimeout
    from tissuecast.evaluate.mismatch import ReferenceSolver, keep_answers_of_one_path, solve_path

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--cache", default="")
    ap.add_argument("--reference", choices=("refined", "p2"), default="refined",
                    help="refined: P2 on the uniformly refined mesh; p2: P2 on the store's mesh (no refined solve)")
    ap.add_argument("--model", action="append", default=[], metavar="LABEL=DIR",
                    help="evaluate a model against the store's fields and the reference's")
    ap.add_argument("--time-limit", type=float, default=900.0,
                    help="wall-clock limit of one solve, s (0: none); a sample past it is left out")
    args = ap.parse_args(argv)
    time_limit = args.time_limit if args.time_limit > 0 else None
    ds = open_dataset(args.store)
    if args.reference == "p2" and ds.config.solver.order == 2:
        raise SystemExit("the store's elements are quadratic already: --reference p2 would compare it with itself; "
                         "use --reference refined")
    cache = Path(args.cache or Path(args.store).with_suffix(".discretisation"))
    cache.mkdir(parents=True, exist_ok=True)
    keep_answers_of_one_path(cache, {"path": solve_path(ds.config)})
    kinds = (("p2",) if ds.config.solver.order == 1 else ()) + (("refined",) if args.reference == "refined" else ())
    solvers = {kind: ReferenceSolver(ds, kind) for kind in kinds}
    rows: dict[str, list] = {}
    t0 = time.perf_counter()
    held = np.union1d(*(np.asarray(ds.scenario_arrays.get(key, []), dtype=np.int64) for key in ("pinned", "attached")))
    supports = ds.mesh.points[held]
    kept, fields = [], {"data": [], "reference": []}
    for k in ds.select("test1", status="done")[: args.samples]:
        try:
            a = _answers(ds, int(k), solvers, cache, args.reference, time_limit)
        except ConvergenceError as exc:
            why = "ran past --time-limit" if isinstance(exc, SolveTimeout) else "did not converge"
            print(f"sample {int(k)}: a solve {why} ({exc}); left out", flush=True)
            continue
        kept.append(int(k))
        for key in fields:
            fields[key].append(a[key])
        ref = a["reference"]
        peak = float(np.linalg.norm(ref, axis=1).max())
        for name in ("data", "p2"):
            if name in a and not (args.reference == "p2" and name == "p2"):
                e = np.linalg.norm(a[name] - ref, axis=1)
                e_flex, angle = _after_rigid(ds.mesh.points, a[name], ref)
                rows.setdefault(name, []).append((e.max() / peak, np.percentile(e, 95), e.mean(),
                                                  e_flex.max() / peak, angle))
        worst = ds.mesh.points[int(np.argmax(np.linalg.norm(a["data"] - ref, axis=1)))]
        to_supports = np.linalg.norm(supports - worst, axis=1).min() if len(supports) else float("nan")
        to_contact = float("nan") if a["contact"] is None else np.linalg.norm(ds.mesh.points[a["contact"]] - worst)
        r = rows["data"][-1]
        print(f"sample {int(k)}: peak {peak:.2f} mm, data's largest error {100 * r[0]:.1f} % of it "
              f"({100 * r[3]:.1f} % after a rigid fit, which turns it by {r[4]:.2f} deg), "
              f"{to_supports:.1f} mm from the supports and {to_contact:.1f} mm from the instrument's contact "
              f"({time.perf_counter() - t0:.0f} s so far)", flush=True)
    order = "P1" if ds.config.solver.order == 1 else "P2"
    labels = {"data": f"the data set ({order}, this mesh)", "p2": "P2, this mesh"}
    where = "the refined mesh" if args.reference == "refined" else "this mesh"
    print(f"\nagainst P2 on {where}, {len(rows['data'])} test-1 samples:")
    print("variant                      max error / peak: median  p95    within 2 %   p95 vertex error  mean error"
          "   after a rigid fit: max / peak median, angle median")
    for name, r in rows.items():
        r = np.asarray(r)
        print(f"{labels[name]:<28} {100 * np.median(r[:, 0]):6.1f} %  {100 * np.percentile(r[:, 0], 95):6.1f} %  "
              f"{100 * np.mean(r[:, 0] <= 0.02):6.0f} %      {np.median(r[:, 1]):.3f} mm         "
              f"{np.median(r[:, 2]):.3f} mm     {100 * np.median(r[:, 3]):6.1f} %, {np.median(r[:, 4]):.2f} deg")
    if args.model and kept:
        _models_against(ds, kept, fields, args.model)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
