"""``tissuecast dataset info|export``: inspect a data set, export a sample for ParaView."""

from __future__ import annotations

import numpy as np

from ..evaluate import json_output
from ..errors import DatasetError, MeshError

#: Failed samples listed by ``dataset info`` (all of them are in the store), and the characters
#: of each reason shown (one terminal line).
FAILURES_SHOWN = 10
REASON_CHARS = 160


def register(sub) -> None:
    p = sub.add_parser("dataset", help="inspect a data set or export one sample")
    dsub = p.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)
    info = dsub.add_parser("info", help="counts by split and status, displacement statistics, timing")
    info.add_argument("store", help="data-set store directory")
    info.add_argument("--json", action="store_true", help="print the figures as JSON")
    info.add_argument("--load-shares", type=int, default=0, metavar="N",
                      help="also solve the first N samples with each load alone (surface field, gravity change, "
                           "instrument) and print each one's share of the peak displacement (N x 4 solves)")
    info.set_defaults(func=run_info)
    ex = dsub.add_parser("export", help="write one sample's deformed mesh (displacement and force point data)")
    ex.add_argument("store", help="data-set store directory")
    ex.add_argument("--sample", type=int, required=True, metavar="I", help="0-based sample index")
    ex.add_argument("output", help="output mesh file, e.g. sample.vtu (ParaView, Slicer)")
    ex.add_argument("--reference", action="store_true",
                    help="write the undeformed mesh (displacement as point data only) instead of the deformed one")
    ex.set_defaults(func=run_export)


def _stats_line(st: dict) -> str:
    if not st:
        return "-"
    return (f"min {st['min']:.2f}  p25 {st['p25']:.2f}  median {st['median']:.2f}  p75 {st['p75']:.2f}  "
            f"p90 {st['p90']:.2f}  p95 {st['p95']:.2f}  max {st['max']:.2f}  (n={st['count']})")


def print_summary(s: dict) -> None:
    """Print a data-set summary (from ``Dataset.summary()``) as text."""
    from ..scenario.describe import scenario_lines

    print(f"data set {s['path']}: {s['n_samples']} samples, {s['n_vertices']} vertices")
    for what, text in scenario_lines(s.get("scenario")):
        print(f"  {what}: {text}")
    print(f"  {'split':<7} {'done':>6} {'failed':>7} {'pending':>8}")
    for name, c in s["counts"].items():
        print(f"  {name:<7} {c['done']:>6} {c['failed']:>7} {c['pending']:>8}")
    t = s["totals"]
    print(f"  {'total':<7} {t['done']:>6} {t['failed']:>7} {t['pending']:>8}")
    cal = s.get("calibration")
    if cal:
        extra = f", q{cal.get('quantile', 0):g} of pilots {cal['quantile_value']:.2f} mm" if cal.get("quantile_value") else ""
        aim = f"; target {cal['target']:g} mm" if cal.get("target") is not None else ""
        print(f"force magnitude alpha = {cal['alpha']:.6g} N ({cal['rule']}{aim}{extra}; the whole set's below)")
        if cal.get("limited_by_failures"):
            print(f"  note: the target {cal['target']:g} mm was not reached: pilot samples failed to converge at "
                  "larger forces (see the calibration rounds in `dataset info --json`)")
    print("per-sample max displacement (mm), done samples:")
    print(f"  all     {_stats_line(s['max_displacement'])}")
    for name, st in s["max_displacement_by_split"].items():
        if st:
            print(f"  {name:<7} {_stats_line(st)}")
    for beta, st in s["max_displacement_by_beta"].items():
        print(f"  beta={beta:<4} median {st['median']:.2f}  max {st['max']:.2f}  (n={st['count']})")
    if s.get("nonrigid_part"):
        print("per-sample non-rigid part (mm): largest vertex residual after the best rigid fit of the whole field")
        print(f"  all     {_stats_line(s['nonrigid_part'])}")
        for name, st in s["nonrigid_part_by_split"].items():
            if st:
                print(f"  {name:<7} {_stats_line(st)}")
        sh = s["nonrigid_share"]
        print(f"  as a share of the sample's peak displacement: p25 {100 * sh['p25']:.0f} %  median "
              f"{100 * sh['median']:.0f} %  p75 {100 * sh['p75']:.0f} %  (a body that mostly swings rigidly has a small "
              "share; rigid registration from the markers is then a strong baseline)")
    tm = s["timing"]
    if tm["solved"]:
        print(f"solver: {tm['seconds_mean']:.2f} s/sample mean (max {tm['seconds_max']:.2f} s, total "
              f"{tm['seconds_total']:.0f} s of worker time), {tm['increments_mean']:.1f} increments and "
              f"{tm['iterations_mean']:.1f} Newton iterations per done sample, {tm['retried']} retried")
    pr = s.get("predictor") or {}
    if pr.get("model"):
        m = pr["model"]
        print(f"reduced-model predictor: {m['modes']} modes from {m['snapshots']} samples, {m['elements']} ECSW "
              f"elements (force error {m['fit_error']:.3g})")
    for key, label in (("from_zero", "from zero"), ("predicted", "from the prediction"),
                       ("prediction_failed", "prediction failed, from zero"),
                       ("from_previous_round", "pilots, from previous round")):
        st = pr.get(key) or {}
        if st.get("samples") and pr.get("model"):
            print(f"  {label:<29} {st['samples']:>6} samples, {st['seconds_mean']:.2f} s, "
                  f"{st['iterations_mean']:.1f} iterations, {st['factorizations_mean']:.1f} factorisations each")
    if s["failures"]:
        print(f"failed samples ({len(s['failures'])}, excluded from select(status='done')):")
        for i, reason in list(s["failures"].items())[:FAILURES_SHOWN]:
            print(f"  {i}: {reason[:REASON_CHARS]}")


def run_info(args) -> int:
    from ..dataset import open_dataset

    ds = open_dataset(args.store)
    s = ds.summary(deformation=True)
    if args.load_shares > 0:
        s["load_shares"] = _load_shares(ds, args.load_shares)
    if args.json:
        print(json_output.dumps(s, indent=2))
        return 0
    print_summary(s)
    if "load_shares" in s:
        from ..scenario.load_shares import format_load_shares

        print("each load alone (nominal parameters):")
        for line in format_load_shares(s["load_shares"]):
            print(f"  {line}")
    return 0


def _load_shares(ds, count: int) -> dict:
    """Each load's share of the peak displacement on the data set's first ``count`` samples."""
    from ..errors import DatasetError
    from ..fem.linear import one_blas_thread
    from ..scenario import restore_scenario
    from ..scenario.load_shares import load_shares

    alpha = float((ds.calibration or {}).get("alpha", 0.0))
    if not alpha > 0 and ds.config.scenario.lbo_forces:
        raise DatasetError("--load-shares needs the store's calibrated force magnitude; simulate the store first")
    scenario = restore_scenario(ds.mesh, ds.config, ds.scenario_arrays, ds.basis)
    with one_blas_thread():
        return load_shares(scenario, ds.config, [int(x) for x in ds.seed[:count]], alpha)


def run_export(args) -> int:
    from ..dataset import SampleStatus, open_dataset
    from ..mesh import write_mesh

    ds = open_dataset(args.store)
    i = args.sample
    if not 0 <= i < ds.n_samples:
        raise DatasetError(f"sample {i} does not exist; the data set has samples 0..{ds.n_samples - 1}")
    if ds.status[i] != SampleStatus.DONE:
        state = SampleStatus(int(ds.status[i])).label
        raise DatasetError(f"sample {i} is {state}, so it has no displacement; pick a done sample "
                           "(`tissuecast dataset info` lists the counts)")
    u = np.asarray(ds.displacements[i], dtype=np.float64)
    f = np.asarray(ds.forces[i], dtype=np.float64)
    mesh = ds.mesh
    if not args.reference:
        try:
            mesh = ds.mesh.deformed(u)
        except MeshError as exc:  # a (near-)degenerate deformed tet: fall back to the reference shape
            print(f"note: writing the undeformed mesh with displacement point data ({exc})")
    files = write_mesh(args.output, mesh, point_data={"displacement": u, "force": f,
                                                      "displacement_magnitude": np.linalg.norm(u, axis=1)})
    print(f"wrote sample {i} ({ds.split[i]}, max displacement {float(np.linalg.norm(u, axis=1).max()):.2f} mm) "
          f"to {', '.join(str(p) for p in files)}")
    return 0
