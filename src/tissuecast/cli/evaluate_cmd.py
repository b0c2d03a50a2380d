"""``tissuecast evaluate MODEL``: accuracy on the data set (the MLP next to rigid registration,
ridge and the PCA floor; Offset_max / Offset_mean over the vertices, TRE and the share of the
displacement corrected at targets) and the HTML report."""

from __future__ import annotations

import sys
from pathlib import Path

from ..evaluate import json_output
from ..config import EvaluateConfig
from .help_examples import with_examples


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast evaluate runs/quick/model",
     "the report (HTML) beside the model, on the store it was trained on"),
    ("tissuecast evaluate runs/quick/model --targets tumour.mrk.json --json",
     "TRE at your own targets (Slicer markups), the evaluation printed as JSON"),
)


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="evaluate a model on its data set and write the report",
                       description="Offset_mean / Offset_max on valid, test-1 and test-2 (per beta), and the target "
                                   "registration error (TRE mean / p95 / max) with the share of the targets' displacement "
                                   "corrected: the MLP next to rigid registration from the same markers, the ridge baseline "
                                   "and the PCA floor, with the peak displacement and non-rigid part of the samples; "
                                   "prediction time; writes index.html (headline, interactive 3D view, figures, renders) "
                                   "and VTU files.", **with_examples(*EXAMPLES))
    p.add_argument("model", help="model folder (from `tissuecast train`)")
    p.add_argument("--store", help="data-set store (default: the store the model was trained on)")
    p.add_argument("--out", help="report folder (default: the model folder's sibling 'report')")
    p.add_argument("--renders", type=int, default=EvaluateConfig.renders,
                   help=f"samples rendered in 3D (default {EvaluateConfig.renders}; 0 = none)")
    p.add_argument("--studies", help="folder with study_*.csv to include (default: the report folder)")
    p.add_argument("--targets", metavar="FILE",
                   help="target points where TRE is measured: CSV (x, y, z or label, x, y, z; LPS mm) or Slicer markups "
                        "(.mrk.json, .fcsv); default the model config's [evaluate.targets] (interior points)")
    p.add_argument("--json", action="store_true", help="print the evaluation as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..dataset import open_dataset
    from ..errors import ModelError
    from ..app.pipeline import evaluate_and_report
    from ..evaluate.report import format_evaluation
    from ..evaluate.targets import model_targets
    from ..surrogate import DeformationModel

    model = DeformationModel.load(args.model)
    store = args.store or model.dataset_path or ((model.run_config or {}).get("dataset") or {}).get("store")
    if not store:
        raise ModelError("the model does not record its data set; pass --store PATH")
    ds = open_dataset(store)
    differ = _simulator_differences(model, ds)
    if differ:
        print(f"warning: {store} was simulated with other physics than the model's training data ("
              f"{', '.join(differ[:4])}{', ...' if len(differ) > 4 else ''} differ): the figures below measure that "
              "mismatch, not the model on its own simulator (`tissuecast study mismatch` measures such sets on "
              "purpose)", file=sys.stderr)
    out = Path(args.out) if args.out else Path(args.model).resolve().parent / "report"
    targets = model_targets(model, points=args.targets)
    evaluation, index = evaluate_and_report(model, ds, out, renders=args.renders, studies_folder=args.studies,
                                            targets=targets)
    if args.json:
        print(json_output.dumps({**evaluation.as_dict(), "report": str(index)}, indent=2, default=float))
    else:
        print(format_evaluation(evaluation))
        print(f"report: {index}")
    return 0


def _simulator_differences(model, dataset) -> list[str]:
    """The keys of ``[material]``, ``[solver]``, ``[forces]`` and ``[scenario]`` in which the
    store's config differs from the one the model was trained with (the store's samples, seeds
    and size may differ freely; the mesh is checked by fingerprint); [] where the model records none."""
    from ..config import config_from_dict
    from ..dataset.store import data_config, data_differences

    if not model.run_config:
        return []
    return [key for key, _, _ in data_differences(data_config(config_from_dict(model.run_config)),
                                                  data_config(dataset.config),
                                                  ("material", "solver", "forces", "scenario"))]

