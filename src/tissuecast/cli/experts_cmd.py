"""``tissuecast experts UNCERTAIN NOMINAL --out FOLDER``: an uncertainty-trained model with a nominal expert.

UNCERTAIN is a model trained on a store with the scenario's parameters drawn
(``[scenario.uncertain]``), NOMINAL one trained on a store of the same scenario at the nominal
parameters, with UNCERTAIN's markers (``[markers] ids``) and instruments. The new model
predicts each sample's field with NOMINAL where a gate, fitted here on the validation splits of
both models' stores, expects it to be the better one, and with UNCERTAIN elsewhere; the alarm
stays UNCERTAIN's, the error bounds are calibrated per route on the samples of UNCERTAIN's store
(:mod:`tissuecast.surrogate.experts`, docs/uncertainty.md).
The folder is a model folder like any other: ``predict``, ``evaluate``, ``serve`` and ``study
mismatch`` take it.
"""

from __future__ import annotations

from pathlib import Path

from ..evaluate import json_output
from ..errors import ModelError


def register(sub) -> None:
    p = sub.add_parser("experts", help="give an uncertainty-trained model a nominal expert and a gate between them",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("uncertain", help="the uncertainty-trained model's folder")
    p.add_argument("nominal", help="the nominal-only model's folder (the same mesh, markers and instruments)")
    p.add_argument("--store", help="the uncertain model's data-set store, whose 'valid' split fits the gate "
                                   "(default: the store the model records)")
    p.add_argument("--nominal-store", help="the nominal model's data-set store, whose 'valid' split fits the gate too "
                                           "(default: the store the nominal model records; 'none': the uncertain "
                                           "store's alone, which sends fewer nominal samples to the expert)")
    p.add_argument("--out", required=True, help="the new model folder")
    p.add_argument("--no-onnx", action="store_true", help="do not write model.onnx (the routed graph of both networks)")
    p.add_argument("--json", action="store_true", help="print the gate's figures as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..app.pipeline import gate_fields
    from ..dataset import open_dataset
    from ..surrogate import DeformationModel
    from ..surrogate.experts import routing_figures

    out = Path(args.out).resolve()
    if out in (Path(args.uncertain).resolve(), Path(args.nominal).resolve()):
        raise ModelError(f"--out {args.out} is one of the two models' folders; write the pair to a folder of its own")
    model, expert = DeformationModel.load(args.uncertain), DeformationModel.load(args.nominal)
    store = args.store or model.dataset_path
    dataset = _open_store(store, args.uncertain, "--store", model.n_vertices)
    theirs = expert.dataset_path
    if not dataset.parameters and theirs and Path(theirs).exists() and open_dataset(theirs).parameters:
        raise ModelError(f"the models look swapped: {args.nominal} was trained on a store that draws parameters, the "
                         f"gate's store {store} draws none; give them in the order UNCERTAIN NOMINAL")
    nominal_store, nominal = None, None
    if args.nominal_store != "none":
        nominal_store = args.nominal_store or theirs
        nominal = _open_store(nominal_store, args.nominal, "--nominal-store", model.n_vertices, hint=NO_NOMINAL_STORE)
        if nominal.parameters:
            raise ModelError(f"the nominal store {nominal_store} draws parameters ({', '.join(sorted(nominal.parameters))}); "
                             "give the store the nominal model was trained on, at the nominal parameters, with "
                             "--nominal-store (and the uncertain model's with --store)")
    fields, aux, drawn = gate_fields(model, dataset, nominal)
    gated = model.with_nominal_expert(expert, fields, auxiliary=aux, drawn=drawn)
    gated.dataset_path = str(Path(store).resolve())
    gated.save(out, onnx=not args.no_onnx)
    figures = {"samples": gated.expert_gate_.samples, "nominal_better": gated.expert_gate_.nominal_better,
               **gated.expert_routes_.summary(), **routing_figures(gated, fields, aux)}
    if args.json:
        print(json_output.dumps({"model": str(Path(args.out)), "store": str(store),
                                 "nominal_store": None if nominal_store is None else str(nominal_store), **figures}, indent=2))
        return 0
    print(f"model with a nominal expert saved to {args.out}")
    stores = store if nominal_store is None else f"{store} and {nominal_store}"
    print(f"  gate fitted on the {figures['samples']} validation samples of {stores}: the nominal expert the better "
          f"one on {100 * figures['nominal_better']:.0f} % of them")
    print(f"  on these samples (the gate's own, so optimistic), mean Offset_max: "
          f"uncertain {figures['uncertain_offset_max']:.2f} mm, nominal {figures['nominal_offset_max']:.2f}, "
          f"routed {figures['routed_offset_max']:.2f} "
          f"({100 * figures['routed_to_nominal']:.0f} % to the nominal expert)")
    print(f"  bounds calibrated per route on the uncertain store's samples, each routed by a gate fitted without it: "
          f"{figures['expert_samples']} to the nominal expert, {figures['model_samples']} to the uncertain model; "
          "the alarm is the uncertain model's. Measure the pair on data it was not fitted on "
          "(`tissuecast evaluate`, `tissuecast study mismatch`)")
    return 0


#: How to go on without the nominal store (said where it is missing).
NO_NOMINAL_STORE = " (or --nominal-store none: the gate on the uncertain store alone, fewer nominal samples to the expert)"


def _open_store(path, model_folder: str, option: str, n_vertices: int, *, hint: str = ""):
    """The data-set store ``path`` a model of ``model_folder`` was trained on, opened and checked:
    it exists and has the model's ``n_vertices`` (errors name ``option``, then ``hint``)."""
    from ..dataset import open_dataset

    if not path:
        raise ModelError(f"{model_folder} records no data-set store; give the one it was trained on with {option}{hint}")
    if not Path(path).exists():
        raise ModelError(f"the store {path} of {model_folder} is not there; give the one it was trained on with "
                         f"{option}{hint}")
    dataset = open_dataset(path)
    if dataset.n_vertices != n_vertices:
        raise ModelError(f"the store {path} has {dataset.n_vertices} vertices, the model {n_vertices}; give the store "
                         f"{model_folder} was trained on ({option})")
    return dataset
