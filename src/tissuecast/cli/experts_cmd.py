"""``tissuecast experts UNCERTAIN NOMINAL --out FOLDER``: an uncertainty-trained model with a nominal expert.

UNCERTAIN is a model trained on a store with the scenario's parameters drawn
(``[scenario.uncertain]``), NOMINAL one trained on a store of the same scenario at the nominal
parameters, with UNCERTAIN's markers (``[markers] ids``) and instruments. The new model
predicts each sample's field with NOMINAL where a gate, fitted here on the validation split of
UNCERTAIN's store, expects it to be the better one, and with UNCERTAIN elsewhere; the error
bounds and the alarm stay UNCERTAIN's (:mod:`tissuecast.surrogate.experts`, docs/uncertainty.md).
The folder is a model folder like any other: ``predict``, ``evaluate``, ``serve`` and ``study
mismatch`` take it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import ModelError


def register(sub) -> None:
    p = sub.add_parser("experts", help="give an uncertainty-trained model a nominal expert and a gate between them",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("uncertain", help="the uncertainty-trained model's folder")
    p.add_argument("nominal", help="the nominal-only model's folder (the same mesh, markers and instruments)")
    p.add_argument("--store", help="the uncertain model's data-set store, whose 'valid' split fits the gate "
                                   "(default: the store the model records)")
    p.add_argument("--out", required=True, help="the new model folder")
    p.add_argument("--json", action="store_true", help="print the gate's figures as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..dataset import open_dataset
    from ..evaluate.evaluation import auxiliary_values
    from ..surrogate import DeformationModel
    from ..surrogate.data import split_indices

    model, expert = DeformationModel.load(args.uncertain), DeformationModel.load(args.nominal)
    store = args.store or model.dataset_path
    if not store:
        raise ModelError(f"{args.uncertain} records no data-set store; give the one it was trained on with --store")
    dataset = open_dataset(store)
    if dataset.n_vertices != model.n_vertices:
        raise ModelError(f"the store {store} has {dataset.n_vertices} vertices, the model {model.n_vertices}; "
                         "give the store the uncertain model was trained on")
    idx = split_indices(dataset, "valid")
    fields = np.asarray(dataset.displacements[idx], dtype=np.float64)
    aux = auxiliary_values(model, dataset)
    aux = None if aux is None else aux[idx]
    gated = model.with_nominal_expert(expert, fields, auxiliary=aux)
    gated.save(args.out)
    figures = _figures(gated, fields, aux)
    if args.json:
        print(json.dumps({"model": str(Path(args.out)), "store": str(store), **figures}, indent=2))
        return 0
    print(f"model with a nominal expert saved to {args.out}")
    print(f"  gate fitted on the {figures['samples']} validation samples of {store}: the nominal expert the better one "
          f"on {100 * figures['nominal_better']:.0f} % of them")
    print(f"  on these samples (the gate's own, so optimistic), mean Offset_max: "
          f"uncertain {figures['uncertain_offset_max']:.2f} mm, nominal {figures['nominal_offset_max']:.2f}, "
          f"routed {figures['routed_offset_max']:.2f} "
          f"({100 * figures['routed_to_nominal']:.0f} % to the nominal expert)")
    print("  bounds and alarm: the uncertain model's; measure the pair on data it was not fitted on "
          "(`tissuecast evaluate`, `tissuecast study mismatch`)")
    return 0


def _figures(gated, fields: np.ndarray, aux) -> dict:
    """The gate's record and the three fields' mean Offset_max (mm) on the gate's samples."""
    d = gated.marker_displacements(fields)
    router = gated.predictor("mlp")
    with gated.gate_suspended():
        to_nominal, mine, theirs = router.routes(d.reshape(len(d), -1), aux)
    worst = {k: float(np.linalg.norm(u - fields, axis=2).max(axis=1).mean()) for k, u in
             (("uncertain", mine.displacement), ("nominal", theirs.displacement),
              ("routed", np.where(to_nominal[:, None, None], theirs.displacement, mine.displacement)))}
    return {"samples": gated.expert_gate_.samples, "nominal_better": gated.expert_gate_.nominal_better,
            "routed_to_nominal": float(to_nominal.mean()), **{f"{k}_offset_max": v for k, v in worst.items()}}
