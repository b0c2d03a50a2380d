"""How the choice of fixed (pinned) vertices shapes the learning problem, measured cheaply.

In linear elasticity a sample's field is ``u = sum_ic W_ic R_ic`` with the 60 unit responses
``R_ic`` (LBO mode i, axis c) of the P2 phantom, so thousands of samples cost 60 back-solves.
For each set of pins this prints, with the fields scaled so that the 0.9 quantile of the
per-sample maximum displacement is 30 mm (the data-set rule):

* the variance share of the first PCA components and the smallest n_w whose reconstruction
  keeps every vertex of 400 held-out samples within 1 mm (the paper's n_w rule; paper: 27);
* the accuracy floor of the markers: test mean Offset_max of the best *linear* estimator of
  the whole field from the 5 markers' displacements (least squares on 1600 samples). In
  linear elasticity this is exact regression, so what remains is what 5 markers cannot see.

Measured on the phantom (2 cores):

=================================  ====  ===================  =====================
pins (0-based)                      n_w   PCA 1-3 variance     5-marker floor
=================================  ====  ===================  =====================
compact [769, 801, 703] (default)   5    46 / 44 / 10 %       0.25 mm, 100 % < 1 mm
spread [1129, 615, 646]             21   87 / 4 / 3 %         2.12 mm, 2 % < 1 mm
near-collinear [769, 1012, 1129]    8    99.5 / 0.1 / 0.1 %   0.46 mm, 100 % < 1 mm
=================================  ====  ===================  =====================

Compact pins: the body swings about a small anchor (three near-rigid rotations carry the
fields); spread pins: it strains in ~60 independent directions that 5 markers cannot see.
The nonlinear data sets agree: test-1 mean Offset_max 2.9-3.2 mm with the spread pins and
0.68 mm with the compact ones after a few hundred training samples.

    python benchmarks/pin_identifiability.py [--fixed 769,801,703 --fixed 1129,615,646]
"""

from __future__ import annotations

import argparse

import numpy as np


def unit_responses(mesh, fixed, basis, youngs_modulus=0.021, poisson_ratio=0.45):
    """(20, 3, n, 3) mm vertex displacements of the small-strain P2 solid under unit LBO modes."""
    from tissuecast.fem import NeoHookean, Problem, Solver
    from tissuecast.forces import lbo_field

    problem = Problem(mesh, NeoHookean(youngs_modulus, poisson_ratio), np.asarray(fixed), order=2)
    solver = Solver(problem)
    assembler, linear = solver.assembler, solver.linear
    _, data, _ = assembler.tangent(np.zeros((assembler.n_nodes, 3)))
    linear.factorize(data)
    n, nb = mesh.n_vertices, basis.n_vectors
    out = np.zeros((nb, 3, n, 3))
    for i in range(nb):
        for c in range(3):
            unit = np.zeros((nb, 3))
            unit[i, c] = 1.0
            f = np.zeros((assembler.n_nodes, 3))
            f[:n] = lbo_field(basis, unit, 1.0, n)
            u = np.zeros(assembler.n_dofs)
            u[assembler.free_dofs] = linear.solve(f.ravel()[assembler.free_dofs])
            out[i, c] = u.reshape(-1, 3)[:n]
    return out


def measure(responses, markers, n_train=1600, n_test=400, seed=0, target=30.0, quantile=0.9) -> dict:
    w = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n_train + n_test,) + responses.shape[:2])
    u = np.einsum("kic,icvd->kvd", w, responses)
    peak = np.linalg.norm(u, axis=2).max(axis=1)
    u *= target / np.quantile(peak, quantile)
    x = u.reshape(len(u), -1)
    train, test = x[:n_train], x[n_train:]
    mean = train.mean(axis=0)
    _, s, vt = np.linalg.svd(train - mean, full_matrices=False)
    n_w = None
    for k in range(1, len(s) + 1):
        rec = (test - mean) @ vt[:k].T @ vt[:k] + mean
        if np.linalg.norm((rec - test).reshape(n_test, -1, 3), axis=2).max() < 1.0:
            n_w = k
            break
    d = u[:, markers].reshape(len(u), -1)
    design = np.hstack([d, np.ones((len(d), 1))])
    coef, *_ = np.linalg.lstsq(design[:n_train], train, rcond=None)
    err = np.linalg.norm((design[n_train:] @ coef - test).reshape(n_test, -1, 3), axis=2).max(axis=1)
    return {"n_w": n_w, "variance_share": (s[:4] ** 2 / np.sum(s**2)).round(3).tolist(),
            "floor_offset_max": float(err.mean()), "floor_share_below_1mm": float(np.mean(err < 1.0))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fixed", action="append", help="comma-separated 0-based fixed vertex ids (repeatable); "
                    "default: the compact and spread rules' pins and the earlier near-collinear ones")
    args = ap.parse_args(argv)

    from tissuecast.config import FIXED_RULES
    from tissuecast.forces import lbo_basis
    from tissuecast.markers import select_fixed_vertices, select_markers
    from tissuecast.mesh.phantom import phantom

    mesh = phantom()
    markers = select_markers(mesh)
    basis = lbo_basis(mesh, 20)
    sets = [[int(v) for v in s.split(",")] for s in args.fixed] if args.fixed else [
        select_fixed_vertices(mesh, exclude=markers, rule=rule).tolist() for rule in FIXED_RULES] + [[769, 1012, 1129]]
    print(f"phantom P2, linear elasticity, markers {markers.tolist()}, fields scaled to q90 max = 30 mm")
    print(f"{'fixed vertices':>22} | {'n_w (<1 mm)':>11} | {'variance of PCA 1-4':>28} | "
          "5-marker floor: mean Offset_max, share < 1 mm")
    for fixed in sets:
        r = measure(unit_responses(mesh, fixed, basis), markers)
        print(f"{str(fixed):>22} | {r['n_w']!s:>11} | {str(r['variance_share']):>28} | "
              f"{r['floor_offset_max']:.2f} mm, {100 * r['floor_share_below_1mm']:.0f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
