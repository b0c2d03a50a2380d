"""What the markers determine: the physics inverse against the trained model, frame by frame.

For test samples of a store, the field from the same marker displacements (and the tracked
instrument) by

- the model (its learned predictor, with its auxiliary inputs), rigid registration and ridge
  from the same markers;
- :class:`tissuecast.inverse.MarkerInverse`: the LBO weights and the unknown parameters whose
  finite-element solution (the store's own simulator) matches the markers; the instrument's
  indentation and the gravity change are the sample's (the indentation is what the tracked pose
  gives; gravity's change is about 1 % of the loads of the shipped presets).

and prints, per sample and over the samples: mean Offset_max, mean Offset_mean and the share
of samples below 1 mm everywhere (mm), the TRE at the model's targets (its evaluation's target
rule: the phantom's 10 interior points) with the share of their displacement corrected
(``tissuecast.evaluate.metrics``), the inverse's marker misfit, its estimated parameters
beside the drawn ones, its time, and the share of the vertices whose error lies within its 90 %
band (:func:`~tissuecast.inverse.spread_band` times its posterior spread). ``--noise MM`` adds
Gaussian noise of that standard deviation to every tracked coordinate (the same draws for
every predictor; the inverse then assumes that noise). ``--split test2`` takes the test-2
samples, whose loads blend in fields outside the LBO family the inverse solves for.
``--simulator TRAINING_STORE`` solves with another store's simulator: for the sets of
``tissuecast study mismatch`` (simulated with one parameter off), the store the model was
trained on, so the inverse assumes what the model assumes.
``--tracked`` gives the inverse what a tracked frame gives ``tissuecast predict --physics``
instead of the sample's own draws: the indentation from the instrument's pose as the store
recorded it (``Scenario.frame_draw``) and gravity in its planned direction (the drawn cone's axis).
A frame has ``--time-limit`` seconds, as in ``predict --physics`` (600 by default; 0 for none).
``--known-margin`` gives the inverse each sample's drawn attached margin, as
``predict --physics --attached-margin`` does a measured one (its held set alone, no search);
``--margin-offset MM`` measures it that far off (clipped to the drawn range) and
``--margin-sd MM`` gives the measurement that standard deviation
(``--attached-margin-sd``: the held sets searched with it as their prior).
``--estimate`` picks the field of a searched frame, as ``predict --physics-estimate``: the
posterior mean over the held sets finished (the default) or the likeliest held set's.

Usage::

    python benchmarks/physics_inverse.py --dataset STORE --model MODEL_FOLDER --samples 20 [--split test2] [--noise 0.25]
    python benchmarks/physics_inverse.py --dataset STUDY/mismatch/attached_minus5_mm.zarr --simulator STORE --model MODEL_FOLDER
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.evaluate.evaluation import auxiliary_values
from tissuecast.evaluate.metrics import share_corrected, target_errors
from tissuecast.evaluate.targets import model_targets
from tissuecast.fem.linear import one_blas_thread
from tissuecast.instruments import recorded_poses
from tissuecast.registration import nonrigid_part
from tissuecast.cli.predict_physics import TIME_LIMIT
from tissuecast.inverse import ESTIMATES, NOISE_MM, MarkerInverse, spread_band
from tissuecast.surrogate import DeformationModel


#: The factor on the inverse's posterior spread of its 90 % band.
BAND = spread_band(0.9)
#: How the inverse is given the loads navigation knows (by ``--tracked``).
KNOWN = {False: "each sample's own draws", True: "as tracked (the instrument's pose, gravity as planned)"}


def errors(field: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(Offset_max, Offset_mean) of one field, mm."""
    e = np.linalg.norm(field - truth, axis=1)
    return float(e.max()), float(e.mean())


def clinical(field: np.ndarray, truth: np.ndarray, targets) -> tuple[float, float]:
    """(mean TRE at the targets mm, share of their displacement corrected) of one field."""
    t_true = targets.displacements(truth[None])
    tre = target_errors(targets.displacements(field[None]), t_true)[0, 0]
    return float(tre), float(share_corrected([tre], [np.linalg.norm(t_true[0], axis=1).mean()])[0])


def summary(rows: np.ndarray) -> str:
    """'mean Offset_max / mean Offset_mean / share < 1 mm; TRE, corrected' of (k, 4) rows."""
    return (f"{rows[:, 0].mean():7.3f} / {rows[:, 1].mean():6.3f} / {100 * np.mean(rows[:, 0] < 1.0):3.0f} %;  "
            f"TRE {rows[:, 2].mean():6.3f} mm, {100 * np.nanmean(rows[:, 3]):5.1f} % corrected")


def given_margin(inv, drawn, s: int, offset: float) -> float:
    """Sample ``s``'s drawn attached margin ``offset`` mm off, clipped to the inverse's range, mm."""
    lo, hi = inv.margin_range
    return float(np.clip(float(drawn["attached_margin"][s]) + offset, lo, hi))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--model", required=True, help="a model folder trained on the store (its markers are used)")
    ap.add_argument("--samples", type=int, default=20, help="the first N samples of the split")
    ap.add_argument("--split", default="test1", choices=("test1", "test2"))
    ap.add_argument("--noise", type=float, default=0.0, help="mm, standard deviation added to each tracked coordinate")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-limit", type=float, default=TIME_LIMIT,
                    help=f"seconds a frame may take, as `predict --physics --time-limit` (default {TIME_LIMIT:g}; 0: none)")
    ap.add_argument("--tracked", action="store_true",
                    help="known loads as a tracked frame gives them (the instrument's pose, gravity as planned), "
                         "not the sample's draws")
    ap.add_argument("--simulator", help="the store whose simulator the inverse solves with (default: --dataset); "
                    "for a mismatch-study set, the store the model trained on, so that the inverse knows no more "
                    "than the model")
    ap.add_argument("--known-margin", action="store_true",
                    help="give the inverse each sample's drawn attached margin (`predict --physics --attached-margin`): "
                         "what a measured attachment is worth")
    ap.add_argument("--margin-offset", type=float, default=0.0,
                    help="with --known-margin: give each margin this many mm off (clipped to the drawn range)")
    ap.add_argument("--margin-sd", type=float,
                    help="with --known-margin: the measured margin's standard deviation, mm (`--attached-margin-sd`)")
    ap.add_argument("--estimate", choices=ESTIMATES, default=ESTIMATES[0],
                    help="the field of a searched frame, as `predict --physics-estimate` (default %(default)s)")
    args = ap.parse_args(argv)

    ds = open_dataset(args.dataset)
    model = DeformationModel.load(args.model)
    mk = model.markers
    idx = np.asarray(ds.select(args.split, status="done"), dtype=np.int64)[: args.samples]
    U = np.asarray(ds.displacements[idx], dtype=np.float64)
    d = U[:, mk] + np.random.default_rng(args.seed).normal(0.0, args.noise, (len(idx), len(mk), 3))
    aux = auxiliary_values(model, ds)
    with model.gate_suspended():
        net = model.predict(d, auxiliary=None if aux is None else aux[idx])
    rigid = model.predict_rigid(d)
    ridge = model.predict_ridge(d)
    sim = open_dataset(args.simulator) if args.simulator else ds
    inv = MarkerInverse.from_dataset(sim, mk, noise=args.noise if args.noise > 0 else NOISE_MM)
    drawn = ds.parameters
    if args.known_margin and "attached_margin" not in drawn:
        ap.error(f"--known-margin: {args.dataset} records no drawn attached margin")
    if (args.margin_offset or args.margin_sd is not None) and not args.known_margin:
        ap.error("--margin-offset and --margin-sd describe the measured margin: give --known-margin")
    targets = model_targets(model)
    measured = (f" {args.margin_offset:+g} mm off" if args.margin_offset else "") + (
        f" +- {args.margin_sd:g} mm" if args.margin_sd is not None else "")
    searched = f"; the field the {args.estimate} estimate"
    margin = ("" if not inv.margins.size else searched if not args.known_margin
              else f"; each sample's margin given{measured}" + (searched if args.margin_sd is not None else ""))
    print(f"{args.dataset}: {len(idx)} {args.split} samples, {len(mk)} markers, noise {args.noise} mm, "
          f"known loads {KNOWN[args.tracked]}, "
          f"alpha {inv.alpha:.4g} N, estimated: W ({3 * inv.n_basis}), "
          f"{', '.join(inv.estimated) or 'no parameter'}"
          f"{', the attached margin (' + str(len(inv.margins)) + ' held sets)' if inv.margins.size else ''}{margin}")
    rows, covered = [], []
    t_all = time.perf_counter()
    for k, s in enumerate(idx):
        known = inv.known_draw(int(ds.seed[s]))
        if args.tracked:
            known = inv.scenario.frame_draw(recorded_poses(ds.instrument_poses, s))
        with one_blas_thread():  # as the data set's workers and `predict --physics` solve
            res = inv.solve(d[k], known, time_limit=args.time_limit or None,
                            attached_margin=given_margin(inv, drawn, s, args.margin_offset) if args.known_margin else None,
                            attached_margin_sd=args.margin_sd,
                            estimate=args.estimate)
        row = [v for f in (res.field, net[k], rigid[k], ridge[k]) for v in (*errors(f, U[k]), *clinical(f, U[k], targets))]
        rows.append(row)
        covered.append(res.within_band(U[k]))
        p = res.parameters
        truth = {name: float(v[s]) for name, v in drawn.items()}
        est = " ".join(f"{name} {getattr(p, name):.3g} ({truth[name]:.3g})" for name in truth
                       if name in ("youngs_modulus", "spring_normal", "spring_tangential", "poisson_ratio",
                                   "attached_margin"))
        print(f"  {k:3d} peak {np.linalg.norm(U[k], axis=1).max():5.1f}  inverse {row[0]:6.3f}/{row[1]:5.3f}  "
              f"model {row[4]:6.3f}/{row[5]:5.3f}  rigid {row[8]:6.2f}  ridge {row[12]:6.2f}  "
              f"marker miss {res.marker_misfit:.3f}  "
              f"band {BAND * np.median(res.spread):.3f} mm covers {100 * covered[-1]:3.0f} %  "
              f"{res.solves} solves {res.seconds:.0f} s"
              f"{'' if res.complete else ' (time limit)'}  {est}", flush=True)
    r = np.array(rows)
    peaks = np.linalg.norm(U, axis=2).max(axis=1)
    nonrigid = nonrigid_part(ds.mesh.points, U)
    print(f"\nmean Offset_max / mean Offset_mean / share below 1 mm; TRE at {targets.description} "
          f"({len(idx)} {args.split} samples, "
          f"median peak {np.median(peaks):.1f} mm, its non-rigid part {np.median(nonrigid):.1f} mm; "
          f"{time.perf_counter() - t_all:.0f} s):")
    for name, cols in (("physics inverse", slice(0, 4)), ("model", slice(4, 8)), ("rigid registration", slice(8, 12)),
                       ("ridge", slice(12, 16))):
        print(f"  {name:20s} {summary(r[:, cols])}")
    c = np.array(covered)
    print(f"the inverse's 90 % band ({BAND:.2f} x its posterior spread) covers {100 * c.mean():.1f} % of the vertices "
          f"(frames {100 * c.min():.0f}-{100 * c.max():.0f} %; {int(np.sum(c < 0.8))} of {len(c)} below 80 %)")


if __name__ == "__main__":
    main()
