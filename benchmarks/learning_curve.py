"""Learning curve: the model's test-1 accuracy against the number of training samples, and what
the samples cost.

The training pool is the store's 'train' split, then every converged sample of the ``--extra``
stores (the same scenario with another ``dataset.seed`` and the store's calibrated
``dataset.alpha``, so that their samples come from the same distribution; e.g.
``split = [1, 0, 0]`` and ``n_test2 = 0``); a size N trains on the first N of the pool. Every
size validates on the store's 'valid' split and is tested on its 'test-1' split, so the rows
differ only in the training set. The models read the markers and the scenario's tracked
instruments' poses (``--markers-only``: the markers alone); the markers are the k-center
rule's, or with ``--planned`` planned on the store as ``markers.rule = "planned"`` plans them.
Each row: decoder, N, markers, the model's test-1 mean
Offset_max, mean Offset_mean, share of samples below 1 mm, the ridge and rigid-registration
baselines' mean Offset_max, n_w after the validation cut, the fit time, and the solver time the N samples
cost (the stores' recorded worker seconds per sample).

Usage::

    python benchmarks/learning_curve.py --dataset runs/embedded/dataset.zarr \\
        --extra runs/embedded/extra.zarr --sizes 800 1600 3200 6400 --markers 10 --variants pca local
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tissuecast.dataset import open_dataset
from tissuecast.evaluate.studies import study_markers
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.auxiliary import AuxiliaryInputs, AuxiliaryValues
from tissuecast.surrogate.data import dataset_arrays, dataset_auxiliary, split_indices

from decoder_floor import errors, parse_variant


def pool(main, extras, inputs: AuxiliaryInputs):
    """``(fields (N, n, 3) mm, auxiliary inputs (N, n_a) or None, training pool ids, valid ids,
    test-1 ids, solver seconds per sample)``; the auxiliary inputs are those ``inputs`` names
    (the scenario's tracked instruments)."""
    a = dataset_arrays(main)
    parts = [np.asarray(a.displacements, dtype=np.float64)]
    aux = [dataset_auxiliary(main, inputs).values] if inputs.width else []
    seconds = [_solver_seconds(main, np.arange(len(parts[0])))]
    ids = [np.asarray(a.train_idx)]
    offset = len(parts[0])
    for ds in extras:
        if ds.mesh.n_vertices != main.mesh.n_vertices:
            raise SystemExit(f"{ds} is not on the mesh of {main}")
        done = ds.select(status="done")
        parts.append(np.asarray(ds.displacements[done], dtype=np.float64))
        if inputs.width:
            aux.append(dataset_auxiliary(ds, inputs).values[done])
        seconds.append(_solver_seconds(ds, done))
        ids.append(offset + np.arange(len(done)))
        offset += len(done)
    return (np.concatenate(parts), np.concatenate(aux) if aux else None, np.concatenate(ids), np.asarray(a.valid_idx),
            split_indices(main, "test1"), np.concatenate(seconds))


def _solver_seconds(ds, idx: np.ndarray) -> np.ndarray:
    """Worker seconds (solver time) of the store's samples ``idx``."""
    from tissuecast.dataset.store import open_root

    return np.asarray(open_root(ds.path)["samples/seconds"][...], dtype=np.float64)[idx]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--extra", nargs="*", default=[])
    p.add_argument("--sizes", type=int, nargs="+", default=[800, 1600, 3200, 6400])
    p.add_argument("--markers", type=int, nargs="+", default=[10])
    p.add_argument("--variants", nargs="+", default=["pca", "local"], help="decoders (decoder_floor.py's NAME[:key=value...])")
    p.add_argument("--markers-only", action="store_true", help="leave the scenario's tracked instruments out")
    p.add_argument("--planned", action="store_true", help="markers planned on the store (markers.rule = 'planned') "
                   "instead of the k-center rule's")
    args = p.parse_args()
    main_ds = open_dataset(args.dataset)
    inputs = AuxiliaryInputs() if args.markers_only else AuxiliaryInputs.from_config(main_ds.config.scenario)
    inputs = AuxiliaryInputs(instruments=inputs.instruments)  # instruments only: measured parameters are not tracked
    U, A, train_pool, valid, test, seconds = pool(main_ds, [open_dataset(e) for e in args.extra], inputs)
    bench = U[test]
    mesh, fixed = main_ds.mesh, np.asarray(main_ds.fixed, dtype=np.int64)
    if args.planned:  # as markers.rule = "planned": surface markers, markers.min_distance apart, from 'train'/'valid'
        from tissuecast.planning import plan_markers

        spacing = main_ds.config.markers.min_distance
        chosen = {n: plan_markers(main_ds, n, region="surface", min_distance=spacing).markers for n in args.markers}
    else:
        ranked = study_markers(mesh, max(args.markers), main_ds.config, exclude=fixed)[0]
        chosen = {n: ranked[:n] for n in args.markers}
    print(f"{main_ds} + {len(train_pool) - len(dataset_arrays(main_ds).train_idx)} extra training samples; "
          f"valid {len(valid)}, test-1 {len(test)}; solver {np.median(seconds):.2f} s a sample (median worker time); "
          f"inputs: {'planned' if args.planned else 'k-center'} markers{''.join(' + ' + i.name for i in inputs.instruments)}")
    print("decoder                 N    n_d  model: Offset_max  Offset_mean  <1 mm   ridge   rigid   n_w   fit s   solve s")
    for n in args.sizes:
        if n > len(train_pool):
            print(f"  N = {n}: only {len(train_pool)} training samples in the pool; skipped")
            continue
        for n_d in args.markers:
            markers = chosen[n_d]
            for label, o in (parse_variant(v) for v in args.variants):
                t0 = time.perf_counter()
                m = DeformationModel(main_ds.config, **{"ensemble": 1, "calibration_share": 0.0, **o}).fit(
                    U, markers, mesh=mesh, fixed=fixed, train_idx=train_pool[:n], valid_idx=valid,
                    auxiliary=None if A is None else AuxiliaryValues(inputs, A))
                fit_s = time.perf_counter() - t0
                d = bench[:, markers, :]
                om, mean, share = errors(m.predict(d, auxiliary=None if A is None else A[test]), bench)
                ridge = errors(m.predict(d, method="ridge"), bench)[0]
                rigid = errors(m.predict(d, method="rigid"), bench)[0]
                print(f"{label:20s} {n:5d} {n_d:5d}  {om:12.3f} {mean:12.3f} {100 * share:5.0f} % {ridge:7.3f} {rigid:7.3f} "
                      f"{m.n_components:5d} {fit_s:7.0f} {seconds[train_pool[:n]].sum():9.0f}", flush=True)


if __name__ == "__main__":
    main()
