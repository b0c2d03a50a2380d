"""The reduced-order physics' own floor: how close a Galerkin model in a basis of the training
fields comes to a test sample's field when it is given everything about the sample, and how long
it takes.

A physics step at prediction time (the instrument issue's "a few reduced Newton steps with the
markers and the instrument as constraints") solves the simulator's equilibrium in a small basis
instead of the full mesh. Whatever it estimates from the markers, it can be no closer to the truth
than the same reduced model given the sample's own loads, materials, springs, held vertices and
indentation, all of which this benchmark hands it (in surgery they are unknown). For each basis
size r (the leading left singular vectors of the training split's fields over the free dofs) it
prints, on the first ``--samples`` of test-1:

- ``projection``: the true field projected on the basis (the best any field of the basis can be);
- ``proj held``: projected on the sample's constrained basis (below: the best field of it; a
  reduced answer also has the patch column's coefficient pinned);
- ``galerkin``: the reduced equilibrium in the constrained basis, every element (no
  hyper-reduction: its error is the basis's and the Galerkin projection's, its time an upper bound);
- ``springs``: the reduced equilibrium in the training basis itself, the held vertices and the
  patch pulled to their values by springs of 100 mm times the modulus, as the data set's guesses do
  (:meth:`tissuecast.scenario.SampleInputs.reduced_guess`): they give by their reaction over that
  stiffness (a few percent of the peak where the basis spans the field); springs stiff enough not
  to give lock the basis instead;
- ``ecsw``: ``galerkin`` with the ECSW hyper-reduction of :class:`tissuecast.fem.reduced.ReducedModel`
  (element weights fitted to ``--ecsw-snapshots`` training fields at ``--ecsw-tolerance``; the
  basis from those fields too, so r is at most their number).

The sample's held vertices (its attached region's extent) and the indentation's patch are imposed
as a reduced model of varying supports must: the **constrained basis** is the part of the training
basis's span that vanishes there, plus the one field of the span reaching the patch's values in
least squares (its coefficient pinned by very stiff springs, :data:`HOLD_LENGTH`); a test field in
the span then comes back to round-off. The reduced model takes the sample's own E, Poisson's ratio
and springs. Every reduced solve is converged tightly (:data:`SOLVE`). Linear tetrahedra only (the
fields are the vertices' own).

Per row: mean Offset_max and mean Offset_mean (mm) against the stored full solutions, the share
of samples below 1 mm everywhere, the median and 90th percentile of a solve's wall time (ms; the
sample's reduced stiffness at zero and reduced springs included, as they depend on its E, Poisson's
ratio and springs; the constrained basis and the model's construction not), and the samples whose
reduced problem did not converge. With ``--model`` (a model trained on the store) the learned
model, rigid registration and ridge from its markers (and its instruments' recorded poses) stand
beside them on the same samples, with the prediction time of the model's batch a sample.

    python benchmarks/reduced_floor.py runs/embedded/dataset.zarr --modes 40 128 512 --samples 30 \
        --model runs/embedded/model

Run it with one BLAS thread on an otherwise idle machine for the times (set here by default).
"""

from __future__ import annotations

import os
import sys

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from tissuecast.dataset import open_dataset  # noqa: E402
from tissuecast.dataset.worker import Task, context_for  # noqa: E402
from tissuecast.evaluate.evaluation import auxiliary_values  # noqa: E402
from tissuecast.fem.reduced import ReducedModel  # noqa: E402
from tissuecast.registration import nonrigid_part  # noqa: E402

#: mm: the springs pinning the patch field's coefficient in the constrained basis are this length
#: times the modulus (stiff: nothing else in that basis moves the held vertices).
HOLD_LENGTH = 1e6
#: The reduced solves' tolerances, quasi-Newton and its Newton fallback (relative to the reduced
#: load, which the springs' pull toward the held values dominates: the data set's guesses' 3e-4
#: and 1e-2 stop far from equilibrium).
SOLVE = {"bfgs_tolerance": 1e-9, "tolerance": 1e-9}
#: Singular values of the basis at the held dofs below this count as zero (the basis is orthonormal).
NULL_TOLERANCE = 1e-9


def field_errors(fields: dict, truth: dict) -> dict:
    """Mean Offset_max / Offset_mean (mm) and the share below 1 mm of ``fields`` ({id: (n, 3)})
    against ``truth`` (the same ids)."""
    if not fields:
        return {"offset_max_mm": float("nan"), "offset_mean_mm": float("nan"), "below_1mm": float("nan")}
    e = [np.linalg.norm(fields[k] - truth[k], axis=1) for k in fields]
    return {"offset_max_mm": float(np.mean([x.max() for x in e])), "offset_mean_mm": float(np.mean([x.mean() for x in e])),
            "below_1mm": float(np.mean([x.max() < 1.0 for x in e]))}


def training_basis(fields: np.ndarray, free: np.ndarray, r: int) -> np.ndarray:
    """(n_free, r) leading left singular vectors of ``fields`` ((s, n, 3) mm) over the free dofs
    ``free`` (flat dof ids)."""
    x = np.asarray(fields, dtype=np.float64).reshape(len(fields), -1)[:, free].T
    u, s, _ = np.linalg.svd(x, full_matrices=False)
    return u[:, : min(r, int(np.sum(s > 1e-10 * s[0])))]


def constrained_basis(basis: np.ndarray, free: np.ndarray, n_nodes: int, held: np.ndarray,
                      values: np.ndarray) -> np.ndarray:
    """The orthonormal basis (n_free, r') of the fields in ``basis``'s span that vanish at the
    vertices ``held`` ((k,) ids), plus, where ``values`` ((k, 3) mm) are not all zero, the span's
    least-squares field reaching them there (the one column that moves the held vertices).

    Args:
        basis: (n_free, r) orthonormal columns over the free dofs ``free`` (flat dof ids of
            ``n_nodes`` nodes); dofs of ``held`` that are not free are skipped (their value is 0).
    """
    held = np.asarray(held, dtype=np.int64)
    if not len(held):
        return basis
    pos = np.full(3 * n_nodes, -1)
    pos[free] = np.arange(len(free))
    rows = pos[(3 * held[:, None] + np.arange(3)).ravel()]
    keep = rows >= 0
    vc, vals = basis[rows[keep]], np.asarray(values, dtype=np.float64).ravel()[keep]
    _, sv, wt = np.linalg.svd(vc, full_matrices=True)
    rank = int(np.sum(sv > NULL_TOLERANCE))
    columns = [wt[rank:].T]
    qp = np.linalg.lstsq(vc, vals, rcond=None)[0]
    if np.linalg.norm(qp) > 0:
        columns.append((qp / np.linalg.norm(qp))[:, None])  # in the row space: orthogonal to the null space
    return basis @ np.hstack(columns)


def projected(u: np.ndarray, basis: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(n, 3) mm: the field ``u`` ((n, 3) mm) projected on the orthonormal ``basis`` over the
    free dofs ``free``."""
    p = np.zeros(u.size)
    p[free] = basis @ (basis.T @ u.ravel()[free])
    return p.reshape(-1, 3)


def reduced_answers(ctx, samples: dict, basis, elements, weights, n_vertices: int,
                    exact: bool = True) -> tuple[dict, list, list]:
    """Each sample's reduced equilibrium from its own inputs (``samples``: ``{id:
    SampleInputs}``), its held vertices and patch imposed through :func:`constrained_basis`
    (``exact``) or by the data set's guesses' springs on ``basis`` itself: ``({id: (n, 3) mm},
    [seconds], [ids that failed])``."""
    base = ctx.solver(0)
    free = np.flatnonzero(base.problem.free_mask)
    n_nodes = len(base.problem.nodes)
    fields, seconds, failed = {}, [], []
    for k, inputs in samples.items():
        view = base.with_parameters(*inputs.solver_parameters) if inputs.parameters is not None else base
        b = constrained_basis(basis, free, n_nodes, *inputs.held_values) if exact else basis
        model = ReducedModel(view.problem, b, elements, weights)
        if inputs.parameters is not None:  # the model has the sample's own E: no scaling of the loads
            inputs = dataclasses.replace(inputs, parameters=dataclasses.replace(inputs.parameters, youngs_modulus=1.0))
        t0 = time.perf_counter()
        u = inputs.reduced_guess(model, HOLD_LENGTH, **SOLVE) if exact else inputs.reduced_guess(model, **SOLVE)
        seconds.append(time.perf_counter() - t0)
        if u is None:
            failed.append(k)
        else:
            fields[k] = np.asarray(u[:n_vertices])
    return fields, seconds, failed


def baseline_rows(ds, model_dir: str, test: np.ndarray, truth: dict) -> list:
    """The learned model (ms: its batch's time a sample), rigid registration and ridge on
    ``test`` (ids) from the model's markers, as rows."""
    from tissuecast.surrogate import DeformationModel

    model = DeformationModel.load(model_dir)
    u = np.stack([truth[int(k)] for k in test])
    d = u[:, model.markers]
    aux = auxiliary_values(model, ds)
    t0 = time.perf_counter()
    with model.gate_suspended():
        net = model.predict(d, auxiliary=None if aux is None else aux[test])
    sec = (time.perf_counter() - t0) / len(test)
    out = []
    for name, f in (("model", net), ("rigid", model.predict_rigid(d)), ("ridge", model.predict_ridge(d))):
        fields = {int(k): np.asarray(f[i], dtype=np.float64) for i, k in enumerate(test)}
        out.append(row(name, 0, field_errors(fields, truth), [sec] if name == "model" else None))
    return out


def row(name: str, r: int, errors: dict, seconds=None, failed=(), elements=None) -> dict:
    out = {"method": name, "modes": r, **errors, "failed": list(failed)}
    if seconds:
        out["ms_median"] = 1e3 * float(np.median(seconds))
        out["ms_p90"] = 1e3 * float(np.percentile(seconds, 90))
    if elements is not None:
        out["elements"] = int(elements)
    return out


def show(r: dict) -> str:
    t = f"{r['ms_median']:9.2f} {r['ms_p90']:8.2f}" if "ms_median" in r else f"{'':9s} {'':8s}"
    el = f"{r['elements']:6d}" if "elements" in r else f"{'':6s}"
    modes = f"{r['modes']:6d}" if r["modes"] else f"{'':6s}"
    return (f"{r['method']:<11}{modes}{el} {r['offset_max_mm']:9.3f} {r['offset_mean_mm']:9.4f} "
            f"{100 * r['below_1mm']:6.0f} % {t} {len(r['failed']):7d}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", help="a data set of linear tetrahedra (zarr folder)")
    ap.add_argument("--modes", type=int, nargs="+", default=[40, 128, 512], help="basis sizes (default 40 128 512)")
    ap.add_argument("--samples", type=int, default=30, help="first test-1 samples (default 30)")
    ap.add_argument("--no-galerkin", action="store_true", help="projection rows only (no reduced solves)")
    ap.add_argument("--ecsw-snapshots", type=int, default=0,
                    help="also the hyper-reduced model, fitted to this many training fields (default 0: not)")
    ap.add_argument("--ecsw-tolerance", type=float, default=0.01, help="ECSW relative force error (default 0.01)")
    ap.add_argument("--model", metavar="FOLDER", help="a model trained on the store: it, rigid registration and "
                    "ridge beside the rows")
    ap.add_argument("--json", metavar="FILE", help="also write the rows here")
    args = ap.parse_args(argv)
    if min(args.modes) < 1 or args.samples < 1 or args.ecsw_snapshots < 0 or not 0 < args.ecsw_tolerance < 1:
        ap.error("--modes and --samples must be positive, --ecsw-snapshots >= 0, --ecsw-tolerance in (0, 1)")
    ds = open_dataset(args.store)
    if int(ds.config.solver.order) != 1:
        ap.error(f"{args.store} is solved with order-{ds.config.solver.order} elements; this benchmark reads "
                 "linear tetrahedra's vertex fields")
    train, test = ds.select("train"), ds.select("test1")[: args.samples]
    if len(train) < 2 or not len(test):
        ap.error(f"{args.store} has {len(train)} solved training and {len(test)} test-1 samples; it needs both")
    ctx = context_for(ds.recipe())
    problem = ctx.solver(0).problem
    nv = ds.mesh.n_vertices
    free = np.flatnonzero(problem.free_mask)
    truth = {int(k): np.asarray(ds.displacements[k], dtype=np.float64) for k in test}
    inputs = {int(k): ctx.inputs(Task(int(k), int(ds.seed[k]), float(ds.beta[k]), float(ds.alpha[k]))) for k in test}
    peak = float(np.median([np.linalg.norm(u, axis=1).max() for u in truth.values()]))
    strain = float(np.median(nonrigid_part(ds.mesh.points, np.stack(list(truth.values())))))
    t0 = time.perf_counter()
    full = training_basis(ds.displacements[train], free, max(args.modes))
    print(f"{args.store}: {len(train)} training fields, {len(test)} test-1 samples (median peak {peak:.1f} mm, "
          f"non-rigid part {strain:.1f} mm), {len(free)} free dofs; basis {time.perf_counter() - t0:.0f} s", flush=True)
    print(f"{'method':<11}{'modes':>6}{'elems':>6} {'Offset_max':>9} {'Off_mean':>9} {'<1 mm':>8} {'ms med':>9} "
          f"{'ms p90':>8} {'failed':>7}", flush=True)
    rows, m = [], len(problem.connectivity)
    if args.model:
        rows.extend(baseline_rows(ds, args.model, test, truth))
        for r in rows:
            print(show(r), flush=True)
    for r in args.modes:
        v = full[:, :r]
        rows.append(row("projection", v.shape[1], field_errors({k: projected(u, v, free) for k, u in truth.items()},
                                                               truth)))
        held = {k: projected(u, constrained_basis(v, free, len(problem.nodes), *inputs[k].held_values), free)
                for k, u in truth.items()}
        rows.append(row("proj held", v.shape[1], field_errors(held, truth)))
        print(show(rows[-2]) + "\n" + show(rows[-1]), flush=True)
        if not args.no_galerkin:
            for name, exact in (("galerkin", True), ("springs", False)):
                fields, sec, failed = reduced_answers(ctx, inputs, v, np.arange(m), np.ones(m), nv, exact)
                rows.append(row(name, v.shape[1], field_errors(fields, truth), sec, failed, m))
                print(show(rows[-1]), flush=True)
    if args.ecsw_snapshots:
        snaps = np.asarray(ds.displacements[train[: args.ecsw_snapshots]], dtype=np.float64)
        for r in args.modes:
            if r > len(snaps):
                print(f"ecsw {r:6d}: not fitted, more modes than the {len(snaps)} fields of --ecsw-snapshots", flush=True)
                continue
            t0 = time.perf_counter()
            fit = ReducedModel.fit(problem, snaps, tolerance=args.ecsw_tolerance, max_modes=r)
            took = time.perf_counter() - t0
            fields, sec, failed = reduced_answers(ctx, inputs, fit.basis, fit.elements, fit.weights, nv)
            rows.append(row("ecsw", fit.n_modes, field_errors(fields, truth), sec, failed, len(fit.elements)))
            rows[-1].update(ecsw_snapshots=len(snaps), ecsw_tolerance=args.ecsw_tolerance, fit_seconds=took)
            print(show(rows[-1]) + f"   (fit {took:.0f} s on {len(snaps)} fields)", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"store": str(args.store), "samples": len(test), "median_peak_mm": peak,
                       "median_nonrigid_mm": strain, "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
