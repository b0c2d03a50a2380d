"""A nominal expert and its gate, measured against what a gate that knew could do (issue 31's
nominal cost; the product is `tissuecast experts`, :mod:`tissuecast.surrogate.experts`).

The uncertainty-trained model (``--uncertain``) is given the nominal-only model (``--nominal``,
the same markers and instruments) as an expert, the gate fitted on the validation splits of
``--gate-store`` (the uncertain model's store) and ``--nominal-store`` (the nominal model's) as
`tissuecast experts` does (``--nominal-store none``: the uncertain store's alone, as in session 30). On each stored set
of a `tissuecast study mismatch` folder (``STUDY/mismatch/*.zarr``, every sample in test-1) it
prints the mean Offset_max of both models, of the routed pair and of the per-sample better of
the two (the oracle: the most any gate could get from these two models), the share routed to
the expert, and how often the gate sent a sample to the better of the two. `tissuecast study
mismatch --model pair=FOLDER` gives the routed pair's full row (baselines, TRE, bounds, alarm).

    python benchmarks/expert_gate.py --uncertain UNC_MODEL --nominal NOM_MODEL \\
        --gate-store UNC_STORE --nominal-store NOM_STORE --study STUDY [--sets nominal attached_minus5_mm] \\
        [--out gate.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tissuecast.app.pipeline import gate_fields, split_fields
from tissuecast.dataset import open_dataset
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.experts import routing_figures


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--uncertain", required=True, help="the uncertainty-trained model's folder")
    p.add_argument("--nominal", required=True, help="the nominal-only model's folder (the same markers)")
    p.add_argument("--gate-store", required=True, help="the uncertain model's store: the gate fits on its 'valid' split")
    p.add_argument("--nominal-store", required=True,
                   help="the nominal model's store: the gate fits on its 'valid' split too ('none': the gate store's alone)")
    p.add_argument("--study", required=True, help="a `tissuecast study mismatch` folder (its mismatch/*.zarr sets)")
    p.add_argument("--sets", nargs="*", default=None, help="set folder names (default: every stored set)")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    a = p.parse_args()
    model = DeformationModel.load(a.uncertain)
    nominal = None if a.nominal_store == "none" else open_dataset(a.nominal_store)
    fields, aux, drawn = gate_fields(model, open_dataset(a.gate_store), nominal)
    pair = model.with_nominal_expert(DeformationModel.load(a.nominal), fields, auxiliary=aux, drawn=drawn)
    gate = pair.expert_gate_
    stores = a.gate_store if nominal is None else f"{a.gate_store} and {a.nominal_store}"
    print(f"gate fitted on {gate.samples} validation samples of {stores}: the expert better on "
          f"{100 * gate.nominal_better:.0f} %", flush=True)
    folder = Path(a.study) / "mismatch"
    names = a.sets or sorted(q.name[:-5] for q in folder.glob("*.zarr"))
    head = f"{'set':22s} {'uncertain':>9s} {'nominal':>8s} {'routed':>7s} {'oracle':>7s} {'to nominal':>10s} {'to better':>9s}"
    print(head + "\n" + "-" * len(head))
    rows = {}
    for name in names:
        ds = open_dataset(folder / f"{name}.zarr")
        r = rows[name] = routing_figures(pair, *split_fields(pair, ds, "test1"))
        print(f"{name:22s} {r['uncertain_offset_max']:9.2f} {r['nominal_offset_max']:8.2f} {r['routed_offset_max']:7.2f} "
              f"{r['oracle_offset_max']:7.2f} {100 * r['routed_to_nominal']:9.0f}% {100 * r['routed_to_better']:8.0f}%",
              flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps({"gate_samples": gate.samples, "nominal_better": gate.nominal_better,
                                           "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
