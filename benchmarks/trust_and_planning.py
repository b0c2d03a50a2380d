"""Marker planning, per-vertex error bounds and the out-of-distribution alarm (issue 17).

Prints, for the data-set store given (any preset: the paper's, or a scenario such as
``configs/embedded.toml``):

1. ``--part planning``: test-1 mean Offset_max (mm) versus the number of markers n_d for
   k-center markers (the paper's rule) and planned markers (``tissuecast.planning``:
   QR-shortlisted greedy selection on a quadratic proxy's validation error, then exchanges; one
   plan per count), each with the
   rigid-registration baseline of the same markers, and the MLP confirmed by training one
   network per set. Target: planned reaches the k-center set's error with at most half as
   many markers, or beats it by >= 30 % at the same count.
2. ``--part bounds``: split-conformal bounds on test-1 and per test-2 beta: coverage and
   median bound at 90 % and 95 % nominal, the per-sample Spearman of the largest bound with
   Offset_max (target >= 0.6), the mean per-vertex Spearman, and a reliability table.
   ``--part predictability``: how well any function of the input could rank the per-sample
   error (out-of-fold errors on the training split regressed on the input, or averaged
   over nearest neighbours).
3. ``--part alarm``: false alarms on clean test-1 and detection of (a) two swapped
   markers, (b) one marker displaced 3 mm, (c) loads 1.5x beyond the largest trained load:
   test-1 force fields rescaled to 1, 1.25, 1.5 x the largest training load (Frobenius norm
   of the nodal forces) and, for comparison, 1.5 x their own load (solved as the data set
   solves a sample, its scenario draws included, with only the force magnitude alpha scaled;
   cached in ``--cache``), at the calibrated
   1 % false-alarm rate; detection versus glitch size and load scale; for 3 mm glitches, which
   score raised the alarm and how often it names the displaced marker; (d) tracking noise:
   the alarm rate on test-1 with Gaussian noise of ``--noise`` mm a coordinate on every marker
   (false alarms under tracking), and with ``--mismatch FOLDER`` (a mismatch study's kept sets,
   ``REPORT/mismatch``) the alarm rate of every set at each noise level, with the reasons (far
   from training, markers that disagree, a marker that stood still, two markers exchanged).
   For (a), also how often the swap score names the exchanged pair.

A model reading instruments gets the store's poses with every input. ``--model FOLDER``
measures a saved model (its markers) instead of fitting one for parts 2 and 3.

All lengths in mm. Not run in CI (minutes; part 3's FEM solves take longer the first time).

Usage::

    python benchmarks/trust_and_planning.py --dataset runs/paper/dataset.zarr [--part all | planning bounds alarm]
        [--markers 10] [--json out.json]
    python benchmarks/trust_and_planning.py --dataset runs/embedded/dataset.zarr --model runs/embedded/model \
        --part alarm --skip-fem --mismatch runs/embedded/report/mismatch
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from tissuecast.dataset import open_dataset
from tissuecast.evaluate.evaluation import spearman_rows
from tissuecast.evaluate.headline import ALARM_REASONS
from tissuecast.evaluate.trust_report import bound_figures
from tissuecast.planning.selection import EXCHANGE_ROUNDS
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.conformal import reliability_curve
from tissuecast.surrogate.data import dataset_arrays, dataset_auxiliary, split_indices


def head_override(args) -> dict:
    """``{"head": ...}`` when ``--head`` was given, else nothing (the store's config decides)."""
    return {"head": args.head} if getattr(args, "head", None) else {}


def offsets_max(pred, bench) -> np.ndarray:
    return np.linalg.norm(pred - bench, axis=2).max(axis=1)


def rigid_offset_max(model, d, bench) -> float:
    from tissuecast.errors import RegistrationError

    try:
        return float(offsets_max(model.predict_rigid(d), bench).mean())
    except RegistrationError:
        return float("nan")


# ---------------------------------------------------------------------------------- planning
def part_planning(ds, args, out: dict) -> None:
    from tissuecast.evaluate.studies import study_markers
    from tissuecast.planning import plan_markers

    a = dataset_arrays(ds)
    U = np.asarray(a.displacements, dtype=np.float64)
    t1 = split_indices(ds, "test1")
    bench = U[t1]
    counts = [int(c) for c in args.counts]
    kc, d_min = study_markers(a.mesh, max(counts), ds.config, exclude=a.fixed)
    plans, t_plan = {}, {}
    for k in counts:  # a plan per count: exchanges make plans of different counts un-nested
        t0 = time.perf_counter()
        plans[k] = plan_markers(ds, count=k, region=args.region, min_distance=args.min_distance,
                                exchange_rounds=args.exchange_rounds)
        t_plan[k] = time.perf_counter() - t0
    print(f"\n== 1. marker planning ({args.region} candidates, min spacing {args.min_distance:g} mm, "
          f"{args.exchange_rounds} exchange rounds; plans took {', '.join(f'{t_plan[k]:.0f}' for k in counts)} s) ==")
    print(f"k-center (d_min {d_min:g} mm): {kc.tolist()}")
    for k in counts:
        print(f"planned {k}: {plans[k].markers.tolist()} ({plans[k].exchanged} exchanged)")
    rows = []
    print(f"{'n_d':>3} | {'k-center MLP':>12} {'rigid':>7} {'proxy':>7} | {'planned MLP':>11} {'rigid':>7} {'proxy':>7} | change")
    for k in counts:
        row = {"n_markers": k}
        plan = plans[k]
        for name, mk in (("kcenter", kc[:k]), ("planned", plan.markers)):
            m = DeformationModel(ds.config, ensemble=1, calibration="none", **head_override(args)).fit(
                U, mk, mesh=a.mesh, fixed=a.fixed, train_idx=a.train_idx, valid_idx=a.valid_idx)
            d = bench[:, mk, :]
            row[f"{name}_mlp"] = float(offsets_max(m.predict(d), bench).mean())
            row[f"{name}_rigid"] = rigid_offset_max(m, d, bench) if k >= 3 else float("nan")
            row[f"{name}_proxy_valid"] = float(plan.proxy(mk))
            row[f"{name}_n_w"] = m.n_components
        row["change"] = row["planned_mlp"] / row["kcenter_mlp"] - 1.0
        rows.append(row)
        print(f"{k:3d} | {row['kcenter_mlp']:12.3f} {row['kcenter_rigid']:7.3f} {row['kcenter_proxy_valid']:7.3f} | "
              f"{row['planned_mlp']:11.3f} {row['planned_rigid']:7.3f} {row['planned_proxy_valid']:7.3f} | "
              f"{100 * row['change']:+.0f} %", flush=True)
    print("(MLP and rigid: test-1 mean Offset_max; proxy: validation mean Offset_max of the planner's quadratic proxy)")
    by = {r["n_markers"]: r for r in rows}
    verdicts = []
    for k in counts:
        half = [j for j in counts if 2 * j <= k]
        reach = [j for j in half if by[j]["planned_mlp"] <= by[k]["kcenter_mlp"]]
        beat = by[k]["planned_mlp"] <= 0.7 * by[k]["kcenter_mlp"]
        verdicts.append({"n_markers": k, "planned_half_reaches": min(reach) if reach else None, "beats_by_30pct": bool(beat)})
        print(f"k-center n_d={k}: planned with <= {k // 2} markers reaches it: "
              f"{('yes, with ' + str(min(reach))) if reach else 'no'}; planned beats it by >= 30 % at n_d={k}: "
              f"{'yes' if beat else 'no'}")
    out["planning"] = {"kcenter": kc.tolist(), "planned": {str(k): plans[k].markers.tolist() for k in counts}, "rows": rows,
                       "verdicts": verdicts, "plan_seconds": {str(k): t for k, t in t_plan.items()}, "region": args.region,
                       "exchange_rounds": args.exchange_rounds}


# ---------------------------------------------------------------------------------- predictability
def part_predictability(ds, model, U, out: dict, folds: int = 5) -> None:
    """How far any function of the marker input can rank the model's per-sample error: out-of-fold
    errors of the model's head (or of a quadratic regression, without a head) on the training
    split, regressed on the input (linear, quadratic) or averaged over its nearest neighbours,
    ranked against the model's test-1 Offset_max."""
    from tissuecast.surrogate.quadratic import fit_quadratic
    from tissuecast.surrogate.ridge import marker_columns

    a = dataset_arrays(ds)
    tr, t1 = np.asarray(a.train_idx), split_indices(ds, "test1")
    cols = marker_columns(model.markers)
    flat = U.reshape(len(U), -1)
    X, Y = flat[:, cols], model.network_.basis.transform(flat)
    q = ((model.pca_choice_ or {}).get("head") or {}).get("dims") or 12
    fold = np.random.default_rng(0).permutation(len(tr)) % folds
    oof = np.zeros(len(tr))
    for f in range(folds):
        fit, held = tr[fold != f], tr[fold == f]
        reg = fit_quadratic(X[fit], Y[fit], quadratic_dims=q)
        e = (model.network_.basis.inverse_transform(reg.predict(X[held])) - flat[held]).reshape(len(held), -1, 3)
        oof[fold == f] = np.linalg.norm(e, axis=2).max(axis=1)
    e1 = offsets_max(model.predict(U[t1][:, model.markers, :]), U[t1])
    print(f"\n== 2b. is the per-sample error predictable from the input? ({folds}-fold out-of-fold errors of a "
          f"q = {q} quadratic regression on {len(tr)} training samples) ==")
    rows = {}
    for name, qe in (("linear", 0), ("quadratic q=6", 6)):
        er = fit_quadratic(X[tr], np.log(oof)[:, None], quadratic_dims=qe, ridge=1e-3)
        rows[name] = (float(spearmanr(er.predict(X[t1])[:, 0], e1)[0]), float(spearmanr(er.predict(X[tr])[:, 0], oof)[0]))
    mu, sd = X[tr].mean(axis=0), X[tr].std(axis=0) + 1e-12
    Z, Z1 = (X[tr] - mu) / sd, (X[t1] - mu) / sd
    near = np.argsort(((Z1[:, None, :] - Z[None]) ** 2).sum(axis=2), axis=1)
    for k in (10, 100):
        rows[f"{k} nearest"] = (float(spearmanr(oof[near[:, :k]].mean(axis=1), e1)[0]), float("nan"))
    for name, (test, fit) in rows.items():
        print(f"  {name:14s} Spearman with the model's test-1 Offset_max {test:+.3f}  (in-sample on the OOF errors {fit:+.3f})")
    out["predictability"] = {"head_dims": q, "rows": {k: {"test1": t, "in_sample": f} for k, (t, f) in rows.items()}}


# ---------------------------------------------------------------------------------- bounds
def auxiliary_of(model, ds, idx):
    """(len(idx), n_a) the store's auxiliary inputs (instrument poses) of samples ``idx`` for a
    model that reads some, else None."""
    if not model.auxiliary.width:
        return None
    return dataset_auxiliary(ds, model.auxiliary).values[np.asarray(idx)]


def trust_model(ds, args):
    a = dataset_arrays(ds)
    U = np.asarray(a.displacements, dtype=np.float64)
    if args.model:
        model = DeformationModel.load(args.model)
        if not model.has_trust:
            raise SystemExit(f"{args.model} has no trust layer (bounds and alarm)")
        print(f"\nmodel {args.model}: markers {model.markers.tolist()}, n_w {model.n_components}")
        return model, U
    markers = a.markers
    if args.markers:  # the k-center rule's first N markers instead of the store's
        from tissuecast.evaluate.studies import study_markers

        markers = study_markers(a.mesh, args.markers, ds.config, exclude=a.fixed)[0]
    t0 = time.perf_counter()
    share = {"calibration": "split", "calibration_share": args.calibration_share} if args.calibration_share is not None else {}
    if getattr(args, "alarm_fault_score", False):
        share["alarm_fault_score"] = True
    model = DeformationModel(ds.config, ensemble=args.ensemble, **head_override(args), **share).fit(
        U, markers, mesh=a.mesh, fixed=a.fixed, train_idx=a.train_idx, valid_idx=a.valid_idx)
    if model.trusted_ is None:
        raise SystemExit("the model has no calibration split (surrogate.calibration_share = 0 in the store's config, as "
                         "in the paper preset): give --calibration-share, e.g. 0.125")
    tr = model.training_
    print(f"\nmodel: markers {model.markers.tolist()}, n_w {model.n_components}, ensemble {model.ensemble_size}, "
          f"{tr['n_train']} training / {tr['n_valid']} validation / {tr['n_calibration']} calibration samples "
          f"({time.perf_counter() - t0:.0f} s)")
    return model, U


def part_bounds(ds, model, U, args, out: dict) -> None:
    print("\n== 2. split-conformal per-vertex error bounds ==")
    t1 = split_indices(ds, "test1")
    t2 = split_indices(ds, "test2")
    beta = np.asarray(ds.beta)
    rows = {"test1": bound_figures(model, U[t1], auxiliary=auxiliary_of(model, ds, t1))}
    for b in np.unique(beta[t2]):
        chosen = t2[beta[t2] == b]
        rows[f"test2 beta={b:g}"] = bound_figures(model, U[chosen], auxiliary=auxiliary_of(model, ds, chosen))
    print(f"{'set':14s} {'n':>4s} {'OffMax':>7s} | {'cov 90%':>7s} {'med b90':>7s} | {'cov 95%':>7s} {'med b95':>7s} | "
          f"{'rho sample':>10s} {'rho vertex':>10s}")
    for name, r in rows.items():
        print(f"{name:14s} {r['count']:4d} {r['offset_max']:7.3f} | "
              f"{100 * r['coverage_0.9']:6.1f}% {r['median_bound_0.9']:7.3f} | "
              f"{100 * r['coverage_0.95']:6.1f}% {r['median_bound_0.95']:7.3f} | {r['sample_spearman']:10.3f} "
              f"{r['vertex_spearman']:10.3f}")
    if model.ensemble_size > 1:
        bench = U[t1]
        u, sigma = model.predict_with_uncertainty(bench[:, model.markers, :])
        e = np.linalg.norm(u - bench, axis=2)
        rows["ensemble_sigma_test1"] = {"sample_spearman": float(spearmanr(sigma.max(axis=1), e.max(axis=1))[0]),
                                        "vertex_spearman": float(spearman_rows(sigma, e).mean())}
        print(f"ensemble sigma on test-1 for comparison: rho sample {rows['ensemble_sigma_test1']['sample_spearman']:.3f}, "
              f"rho vertex {rows['ensemble_sigma_test1']['vertex_spearman']:.3f}")
    bench = U[t1]
    d = bench[:, model.markers, :]
    u = model.predict(d)
    sigma = model.trusted_.layer.normaliser(d.reshape(len(d), -1), u)
    lv, emp = reliability_curve(model.trusted_.layer.conformal, np.linalg.norm(u - bench, axis=2), sigma)
    print("reliability on test-1 (nominal -> empirical coverage): "
          + ", ".join(f"{100 * a:.0f}->{100 * b:.1f}" for a, b in zip(lv, emp)))
    out["bounds"] = {"rows": rows, "reliability": {"nominal": lv.tolist(), "empirical": emp.tolist()}}


# ---------------------------------------------------------------------------------- alarm
def swap_markers(d, ref, rng, return_pairs: bool = False):
    """Two random markers' tracked positions exchanged: d (B, n_d, 3) displacements, ref (n_d, 3);
    with ``return_pairs`` also the exchanged pairs (B, 2), i < j."""
    out = d.copy()
    pairs = np.zeros((len(d), 2), dtype=np.int64)
    for b in range(len(d)):
        i, j = sorted(rng.choice(len(ref), 2, replace=False))
        pi, pj = ref[i] + d[b, i], ref[j] + d[b, j]
        out[b, i], out[b, j] = pj - ref[i], pi - ref[j]
        pairs[b] = i, j
    return (out, pairs) if return_pairs else out


def displace_marker(d, size, rng, return_index: bool = False):
    """One random marker moved by ``size`` mm in a random direction (and, if asked, which: (B,))."""
    out = d.copy()
    v = rng.normal(size=(len(d), 3))
    v *= size / np.linalg.norm(v, axis=1, keepdims=True)
    k = rng.integers(0, d.shape[1], len(d))
    out[np.arange(len(d)), k] += v
    return (out, k) if return_index else out


def scaled_load_fields(ds, args) -> dict:
    """FEM fields of test-1 samples whose force field is scaled to ``--load-scales`` x the largest
    training load (Frobenius norm of the nodal forces) and ``--own-scales`` x their own load,
    solved as the data set solves its samples (:func:`tissuecast.dataset.recipe_from_store`:
    the same supports, scenario draws (gravity change, indentation), solver and retries; only
    the force magnitude alpha differs); each solve is cached in ``--cache`` (resumable)."""
    from tissuecast.dataset import recipe_from_store
    from tissuecast.dataset.worker import Task, solve_task

    cache = Path(args.cache) / f"scaled_loads_{ds.path.name}"
    cache.mkdir(parents=True, exist_ok=True)
    F = np.asarray(ds.forces)
    train = split_indices(ds, "train")
    t1 = split_indices(ds, "test1")[: args.load_samples]
    norms = np.sqrt((F.astype(np.float64) ** 2).sum(axis=(1, 2)))
    largest = float(norms[train].max())
    seeds, alphas = np.asarray(ds.seed), np.asarray(ds.alpha, dtype=np.float64)
    recipe = None
    fields, scale_of, sample_of, ok, seconds = [], [], [], [], []
    # positive scale s: the load rescaled to s x the largest training load; negative -s: s x its own load
    for s in [*args.load_scales, *(-x for x in args.own_scales)]:
        for i in t1:
            path = cache / f"scale{s:+g}_sample{i}.npz"
            if not path.is_file():
                if recipe is None:
                    recipe = recipe_from_store(ds.path)
                k = s * largest / norms[i] if s > 0 else -s
                t = time.perf_counter()
                r = solve_task(recipe, Task(int(i), int(seeds[i]), float("nan"), float(alphas[i]) * k))
                good = r.displacement is not None
                u = np.asarray(r.displacement, dtype=np.float64) if good else np.full(F.shape[1:], np.nan)
                np.savez(path, u=u, converged=good, seconds=time.perf_counter() - t)
                label = f"x{s:g} of the largest" if s > 0 else f"x{-s:g} of its own"
                what = f"peak {np.linalg.norm(u, axis=1).max():.1f} mm" if good else "did not converge"
                print(f"  load {label}, sample {i}: {what} ({time.perf_counter() - t:.1f} s)", flush=True)
            with np.load(path, allow_pickle=False) as z:
                fields.append(z["u"])
                ok.append(bool(z["converged"]))
                seconds.append(float(z["seconds"]))
            scale_of.append(s)
            sample_of.append(i)
    return {"fields": np.asarray(fields), "scale": np.asarray(scale_of), "sample": np.asarray(sample_of),
            "converged": np.asarray(ok), "seconds": np.asarray(seconds), "largest_train_load": largest}


def part_alarm_loads(ds, model, args) -> dict:
    """(c) of the alarm: FEM samples under loads scaled beyond the training range; per scale, the share
    detected, the peak displacement, the MLP's error where detected and not, and the bounds' coverage."""
    loads = scaled_load_fields(ds, args)
    ok = loads["converged"]
    train_peak = np.asarray(ds.max_displacement, dtype=np.float64)[split_indices(ds, "train")]
    p95, pmax = np.percentile(train_peak, 95), train_peak.max()
    print(f"training peak displacement: p95 {p95:.1f} mm, max {pmax:.1f} mm")
    rows = {}
    for s in np.unique(loads["scale"]):
        label = f"{s:g}x the largest training load" if s > 0 else f"{-s:g}x its own load"
        pick = (loads["scale"] == s) & ok
        n_all = int((loads["scale"] == s).sum())
        row = {"solved": n_all, "converged": int(pick.sum())}
        if pick.any():
            fields = loads["fields"][pick]
            d = fields[:, model.markers, :]
            aux = auxiliary_of(model, ds, loads["sample"][pick])  # each solve's own sample's instrument poses
            with model.gate_suspended():
                trusted = model.predict_trusted(d, auxiliary=aux)
                err = offsets_max(model.predict(d, auxiliary=aux), fields)
            raised = np.array([a.raised for a in trusted.alarms])
            cover = float(np.mean(np.linalg.norm(trusted.displacement - fields, axis=2) <= trusted.error_bound))
            peak = np.linalg.norm(fields, axis=2).max(axis=1)
            beyond = peak > pmax
            row.update(detected=float(raised.mean()), peak_median=float(np.median(peak)),
                       beyond_training_max=int(beyond.sum()),
                       detected_beyond_max=float(raised[beyond].mean()) if beyond.any() else float("nan"),
                       detected_beyond_p95=float(raised[peak > p95].mean()) if (peak > p95).any() else float("nan"),
                       mlp_offset_max_detected=float(err[raised].mean()) if raised.any() else float("nan"),
                       mlp_offset_max_missed=float(err[~raised].mean()) if (~raised).any() else float("nan"),
                       bound_coverage_90=cover)
            print(f"(c) loads {label}: detected {100 * row['detected']:.1f} % of {row['converged']} converged "
                  f"({n_all - row['converged']} of {n_all} did not converge); median peak {row['peak_median']:.1f} mm; "
                  f"{row['beyond_training_max']} beyond the training max, detected {100 * row['detected_beyond_max']:.0f} %; "
                  f"beyond training p95 detected {100 * row['detected_beyond_p95']:.0f} %; MLP mean Offset_max "
                  f"{row['mlp_offset_max_detected']:.2f} mm where detected, {row['mlp_offset_max_missed']:.2f} where not; "
                  f"90 % bounds cover {100 * cover:.1f} % of vertices")
        else:
            print(f"(c) loads {label}: none of {n_all} converged")
        rows[label] = row
    return rows


def alarm_shares(model, d, aux, alarms=None) -> dict:
    """Share of inputs ``d`` (B, n_d, 3) mm alarmed, alarmed for each reason, refused by the
    input gate, and flagged either way (call with the gate suspended; ``alarms``: their alarms
    where already computed)."""
    refused = np.array([v.refused for v in model.check_input(d)])
    alarms = model.predict_trusted(d, auxiliary=aux).alarms if alarms is None else alarms
    row = {"alarm": float(np.mean([a.raised for a in alarms])), "gate_refused": float(refused.mean()),
           "flagged": float(np.mean(refused | np.array([a.raised for a in alarms])))}
    for key, (reason, _) in ALARM_REASONS.items():
        row[key] = float(np.mean([a.raised and getattr(a, reason) for a in alarms]))
    return row


def part_alarm_noise(ds, model, args) -> dict:
    """(d): alarm rates under Gaussian tracking noise (``args.noise`` mm a coordinate, every
    marker) on clean test-1 and on each kept set of a mismatch study (``args.mismatch``)."""
    rng = np.random.default_rng(23)
    sets = {"test-1 (clean)": ds}
    if args.mismatch:
        for store in sorted(Path(args.mismatch).glob("*.zarr")):
            sets[store.stem] = open_dataset(store)
    levels = [0.0, *args.noise]
    print(f"(d) tracking noise ({', '.join(f'{v:g}' for v in levels)} mm a coordinate on every marker): "
          "alarm rate (far / disagree / still marker / swapped markers)")
    res = {}
    for name, sds in sets.items():
        idx = split_indices(sds, "test1")
        if len(idx) == 0:
            continue
        d = np.asarray(sds.displacements, dtype=np.float64)[idx][:, model.markers, :]
        aux = auxiliary_of(model, sds, idx)
        with model.gate_suspended():  # noisy input the gate would refuse is still an input the alarm sees
            rows = {f"{v:g}": alarm_shares(model, d + rng.normal(0.0, v, d.shape) if v else d, aux) for v in levels}
        res[name] = rows
        print(f"  {name:<28s} " + "  ".join(
            f"{k} mm: {100 * r['alarm']:5.1f} % ({100 * r['alarm_far_rate']:.0f}/{100 * r['alarm_disagree_rate']:.0f}/"
            f"{100 * r['alarm_still_rate']:.0f}/{100 * r['alarm_swap_rate']:.0f})" for k, r in rows.items())
              + (f"; the gate refuses up to {100 * max(r['gate_refused'] for r in rows.values()):.0f} %"
                 if any(r["gate_refused"] for r in rows.values()) else ""))
    return res


def part_alarm(ds, model, U, args, out: dict) -> None:
    rng = np.random.default_rng(17)
    fa = model.config.false_alarm_rate
    print(f"\n== 3. out-of-distribution alarm (threshold for {100 * fa:g} % false alarms, from "
          f"{len(model.trusted_.layer.ood.calibration)} calibration samples) ==")
    ref = model.reference_marker_positions
    t1 = split_indices(ds, "test1")
    d = U[t1][:, model.markers, :]
    aux1 = auxiliary_of(model, ds, t1)

    def rate(dd, aux=aux1) -> float:  # the alarm alone: the input gate would refuse some of these first
        with model.gate_suspended():
            return float(np.mean([a.raised for a in model.predict_trusted(dd, auxiliary=aux).alarms]))

    res = {"false_alarms_test1": rate(d)}
    swaps, named = [], []
    with model.gate_suspended():
        for _ in range(5):
            swapped, pairs = swap_markers(d, ref, rng, return_pairs=True)
            alarms = model.predict_trusted(swapped, auxiliary=aux1).alarms
            swaps.append(alarm_shares(model, swapped, aux1, alarms))
            named += [a.swapped_markers_alarm and (a.swap_first, a.swap_second) == tuple(p) for a, p in zip(alarms, pairs)]
    res["swap"] = float(np.mean([r["alarm"] for r in swaps]))
    res["swap_flagged"] = float(np.mean([r["flagged"] for r in swaps]))  # refused by the input gate or alarmed
    res["swap_named"] = float(np.mean(named))  # the swap score named the exchanged pair
    res["displaced"] = {f"{s:g}": float(np.mean([rate(displace_marker(d, s, rng)) for _ in range(5)]))
                        for s in (0.25, 0.5, 1.0, 2.0, 3.0, 5.0)}
    print(f"clean test-1: false alarms {100 * res['false_alarms_test1']:.1f} % (n = {len(t1)})")
    cons = model.trusted_.layer.ood.consistency
    if cons is not None:  # how far each clean marker lies from where the others put it: the floor of (b)
        miss = cons.residuals(model.trusted_.layer.inputs(d.reshape(len(d), -1), aux1, len(d)))
        res["clean_marker_miss_mm"] = {q: float(np.percentile(miss, v)) for q, v in (("median", 50), ("p90", 90), ("p99", 99))}
        print("clean test-1, each marker predicted from the others misses by (mm): "
              + ", ".join(f"{k} {v:.2f}" for k, v in res["clean_marker_miss_mm"].items()))
    print(f"(a) two markers swapped: detected {100 * res['swap']:.1f} % (5 random swaps per test-1 sample); refused by "
          f"the input gate or alarmed {100 * res['swap_flagged']:.1f} %; the swap score names the pair in "
          f"{100 * res['swap_named']:.1f} %")
    print("(b) one marker displaced, detection by size: "
          + ", ".join(f"{k} mm: {100 * v:.1f} %" for k, v in res["displaced"].items()))
    glitched, which = displace_marker(d, 3.0, rng, return_index=True)
    with model.gate_suspended():
        alarms = model.predict_trusted(glitched, auxiliary=aux1).alarms
    raised = np.array([a.raised for a in alarms])
    named = np.array([a.marker for a in alarms]) == which
    res["displaced_3mm_named"] = float(named[raised].mean()) if raised.any() else float("nan")
    res["displaced_3mm_named_all"] = float(named.mean())
    by_score = {"consistency": [a.consistency > a.consistency_threshold for a in alarms],
                "fault": [a.fault > a.fault_threshold for a in alarms]}
    res["displaced_3mm_by_score"] = {k: float(np.mean(v)) for k, v in by_score.items()}
    fault = (f"{100 * res['displaced_3mm_by_score']['fault']:.1f} %" if model.trusted_.layer.ood.use_fault
             else "- (not in the alarm: --alarm-fault-score)")
    print(f"(b) 3 mm: raised by the consistency score {100 * res['displaced_3mm_by_score']['consistency']:.1f} %, by the "
          f"one-marker fault score {fault}; the alarm names the displaced marker "
          f"in {100 * res['displaced_3mm_named']:.0f} % of the alarms ({100 * res['displaced_3mm_named_all']:.0f} % of all "
          "inputs)")
    t2 = split_indices(ds, "test2")
    beta = np.asarray(ds.beta)
    res["test2_alarm_by_beta"] = {f"{b:g}": rate(U[t2[beta[t2] == b]][:, model.markers, :],
                                                 auxiliary_of(model, ds, t2[beta[t2] == b])) for b in np.unique(beta[t2])}
    print("test-2 alarm rate by beta: " + ", ".join(f"{k}: {100 * v:.0f} %" for k, v in res["test2_alarm_by_beta"].items()))
    res["noise"] = part_alarm_noise(ds, model, args)
    if not args.skip_fem:
        res["loads"] = part_alarm_loads(ds, model, args)
    out["alarm"] = res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True, help="data-set store (tissuecast simulate)")
    p.add_argument("--part", choices=("planning", "bounds", "predictability", "alarm", "all"), nargs="+", default=["all"],
                   help="one or more parts (all = every part)")
    p.add_argument("--counts", type=int, nargs="+", default=[2, 3, 4, 5, 6, 8, 10, 12, 15, 20])
    p.add_argument("--region", default="surface", help="planning candidates: surface, any, interior")
    p.add_argument("--min-distance", type=float, default=0.0, help="planning: minimum marker spacing (mm)")
    p.add_argument("--exchange-rounds", type=int, default=EXCHANGE_ROUNDS, help="planning: exchange passes (0 = greedy only)")
    p.add_argument("--markers", type=int, default=0,
                   help="bounds and alarm: this many k-center markers (as the n_d study picks them) instead of the store's")
    p.add_argument("--head", choices=("quadratic", "none"),
                   help="surrogate.head of the trained models (default: the store's config)")
    p.add_argument("--calibration-share", type=float,
                   help="surrogate.calibration_share of the bounds/alarm model (default: the store's config)")
    p.add_argument("--ensemble", type=int, default=1, help="ensemble size of the model whose bounds are measured")
    p.add_argument("--alarm-fault-score", action="store_true",
                   help="alarm: the single-marker fault score joins the alarm (surrogate.alarm_fault_score)")
    p.add_argument("--load-scales", type=float, nargs="+", default=[1.0, 1.25, 1.5])
    p.add_argument("--own-scales", type=float, nargs="*", default=[1.5],
                   help="also solve the test-1 force fields times these factors of their own magnitude")
    p.add_argument("--load-samples", type=int, default=24, help="test-1 force fields solved per load scale")
    p.add_argument("--cache", default="benchmark-cache", help="folder caching the scaled-load FEM solves")
    p.add_argument("--skip-fem", action="store_true", help="skip the scaled-load FEM solves of part 3")
    p.add_argument("--model", help="bounds and alarm: this saved model folder instead of fitting one")
    p.add_argument("--noise", type=float, nargs="*", default=[0.1, 0.25, 0.5],
                   help="alarm (d): tracking noise levels, mm a coordinate")
    p.add_argument("--mismatch", help="alarm (d): a mismatch study's folder of kept sets (REPORT/mismatch)")
    p.add_argument("--json", help="write every figure to this JSON file")
    args = p.parse_args(argv)
    ds = open_dataset(args.dataset)
    print(repr(ds))
    out: dict = {"dataset": str(args.dataset)}
    parts = {"planning", "bounds", "predictability", "alarm"} if "all" in args.part else set(args.part)
    if "planning" in parts:
        part_planning(ds, args, out)
    if parts & {"bounds", "predictability", "alarm"}:
        model, U = trust_model(ds, args)
        if "bounds" in parts:
            part_bounds(ds, model, U, args, out)
        if "predictability" in parts:
            part_predictability(ds, model, U, out)
        if "alarm" in parts:
            part_alarm(ds, model, U, args, out)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
