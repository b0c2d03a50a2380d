"""The whole run as library calls: data set -> trained model -> evaluation -> report.

No printing here; the CLI (``tissuecast run``, ``demo``, ``train``, ``evaluate``) reports.
Paths: ``config.output`` holds ``model/`` and the report folder ``config.evaluate.output``
(relative to ``config.output`` unless absolute); the store is ``config.dataset.store``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from ..config import Config, EvaluateConfig, config_to_dict, nothing_drawn, with_overrides
from ..errors import ConfigError

__all__ = ["RunPaths", "run_paths", "train_from_store", "planned_config", "chosen_markers_config", "evaluate_and_report",
           "run_pipeline", "resolve_source", "nominal_config", "add_nominal_expert", "gate_fields",
           "split_fields", "PLAN_FILE",
           "NOMINAL_SEED_OFFSET"]

log = logging.getLogger(__name__)

#: The markers' plan (``markers.rule = "planned"``), beside the model: ``tissuecast markers plan``'s JSON.
PLAN_FILE = "markers_plan.json"
#: Added to ``dataset.seed`` for the nominal expert's store (``surrogate.nominal_expert``): its
#: samples are not the uncertain store's.
NOMINAL_SEED_OFFSET = 104729


class RunPaths:
    """Where a run keeps its store, model and report."""

    def __init__(self, config: Config, store=None):
        out = Path(config.output)
        self.output = out
        self.store = Path(store) if store else Path(config.dataset.store)
        #: the nominal expert's store (``surrogate.nominal_expert``): ``dataset_nominal.zarr`` beside ``dataset.zarr``
        self.nominal_store = self.store.with_name(f"{self.store.stem}_nominal{self.store.suffix}")
        self.model = out / "model"
        rep = Path(config.evaluate.output)
        self.report = rep if rep.is_absolute() else out / rep


def run_paths(config: Config, store=None) -> RunPaths:
    return RunPaths(config, store)


def train_from_store(config: Config, store, *, model_folder=None, onnx: bool = True):
    """Fit a :class:`DeformationModel` on a store's train/valid splits and save it.

    Args:
        config: run configuration (its surrogate section is used).
        store: the data-set store path.
        model_folder: where to save (None: do not save).
        onnx: also write ``model.onnx`` into the folder.
    """
    from ..dataset import open_dataset
    from ..surrogate import DeformationModel

    ds = open_dataset(store)
    plan = None
    if config.markers.rule == "planned" and not config.markers.ids:
        config, plan = planned_config(config, ds)
    elif not config.markers.ids and not config.scenario.pins:
        config = chosen_markers_config(config, ds)
    model = DeformationModel.from_dataset(ds, config)
    if model_folder is not None:
        model.save(model_folder, onnx=onnx)
        if plan is not None:
            (Path(model_folder) / PLAN_FILE).write_text(json.dumps(plan.as_dict(), indent=2))
    return model, ds


def nominal_config(config: Config, store, alpha: float) -> Config:
    """The config of the nominal expert's store (``surrogate.nominal_expert``): the scenario with
    no parameter drawn, the force magnitude ``alpha`` (N; the uncertain store's calibrated one:
    the same loads), its own ``store`` and seed (``dataset.seed + NOMINAL_SEED_OFFSET``),
    ``surrogate.nominal_samples`` samples (0: as many as ``dataset.n_samples``) and no test-2
    (the expert trains and the gate fits on its train and valid splits; nothing reads a test-2)."""
    samples = config.surrogate.nominal_samples or config.dataset.n_samples
    return with_overrides(config, scenario={"uncertain": nothing_drawn()},
                          dataset={"store": str(store), "alpha": float(alpha), "n_samples": samples, "n_test2": 0,
                                   "seed": config.dataset.seed + NOMINAL_SEED_OFFSET},
                          surrogate={"nominal_expert": False, "nominal_samples": 0})


def add_nominal_expert(config: Config, model, dataset, nominal_store, *, model_folder=None, onnx: bool = True):
    """``model`` (trained on ``dataset``, parameters drawn) with a nominal expert: a model of the
    same settings trained on ``nominal_store`` with ``model``'s markers, and the gate fitted on
    the validation splits of ``dataset`` and of the nominal store (:func:`gate_fields`,
    :meth:`~tissuecast.surrogate.DeformationModel.with_nominal_expert`); saved into
    ``model_folder`` unless None, with ``onnx`` the routed graph as ``model.onnx``."""
    from ..dataset import open_dataset
    from ..surrogate import DeformationModel, fit_stage

    nominal = open_dataset(nominal_store)
    cfg = with_overrides(nominal.config, markers={"ids": [int(i) for i in model.markers]},
                         surrogate=config_to_dict(config)["surrogate"] | {"nominal_expert": False, "nominal_samples": 0})
    t = time.perf_counter()
    with fit_stage("nominal expert"):
        expert = DeformationModel.from_dataset(nominal, cfg)
    log.info("nominal expert trained on %s in %.1f s", nominal_store, time.perf_counter() - t)
    fields, aux, drawn = gate_fields(model, dataset, nominal)
    pair = model.with_nominal_expert(expert, fields, auxiliary=aux, drawn=drawn)
    if model_folder is not None:
        pair.save(model_folder, onnx=onnx)
    return pair


def gate_fields(model, dataset, nominal=None):
    """``(fields (B, n, 3) float64 mm, auxiliary inputs (B, n_a) or None, drawn (B,) bool)`` that
    the gate of ``model``'s nominal expert is fitted on: the validation split of the uncertain
    store ``dataset`` (``drawn``: these) and, when ``nominal`` is another store, of the expert's
    nominal store. Both families, so that the gate sees the expert win where it does (at and
    near the nominal parameters, a small corner of the drawn ranges; measured in
    docs/uncertainty.md); the pair's bounds are calibrated on the drawn ones alone."""
    fields, aux = split_fields(model, dataset, "valid")
    if nominal is None or Path(nominal.path).resolve() == Path(dataset.path).resolve():
        return fields, aux, np.ones(len(fields), dtype=bool)
    more, more_aux = split_fields(model, nominal, "valid")
    drawn = np.concatenate([np.ones(len(fields), dtype=bool), np.zeros(len(more), dtype=bool)])
    return np.concatenate([fields, more]), None if aux is None else np.concatenate([aux, more_aux]), drawn


def split_fields(model, dataset, split: str):
    """``(fields (B, n, 3) float64 mm, auxiliary inputs (B, n_a) or None)`` of a store's converged
    samples of ``split``, the auxiliary inputs as ``model`` reads them."""
    from ..evaluate.evaluation import auxiliary_values
    from ..surrogate.data import split_indices

    idx = split_indices(dataset, split)
    aux = auxiliary_values(model, dataset)
    return np.asarray(dataset.displacements[idx], dtype=np.float64), None if aux is None else aux[idx]


def chosen_markers_config(config: Config, dataset) -> Config:
    """``config`` with ``markers.ids`` set to the markers its k-center rule chooses on the data
    set's mesh (avoiding the stored attached region), where they differ from the store's.

    Without pins the markers change no sample, so a store resumes under other ``[markers]``
    settings (:func:`tissuecast.dataset.data_config`) and keeps the markers it was made with;
    the model is trained with the ones the config asks for."""
    from ..markers import markers_from_config

    chosen = markers_from_config(dataset.mesh, config.markers, held=dataset.scenario_arrays["attached"])
    if np.array_equal(chosen, dataset.markers):
        return config
    log.info("the data set was made with markers %s; training with the %d the config chooses (0-based ids %s)",
             np.asarray(dataset.markers).tolist(), len(chosen), chosen.tolist())
    return with_overrides(config, markers={"ids": [int(i) for i in chosen]})


def planned_config(config: Config, dataset):
    """``(config with markers.ids planned, MarkerPlan)``: ``markers.count`` surface markers at
    least ``markers.min_distance`` apart, planned from the data set's train/valid fields
    (:func:`tissuecast.planning.plan_markers`; deterministic)."""
    from ..planning import plan_markers

    t = time.perf_counter()
    plan = plan_markers(dataset, config.markers.count, region="surface", min_distance=config.markers.min_distance,
                        sentinel=config.markers.sentinel)
    log.info("planned %d markers from the simulations in %.1f s (proxy validation mean Offset_max %.2f mm): "
             "0-based ids %s", plan.count, time.perf_counter() - t, plan.proxy_error, plan.markers.tolist())
    return with_overrides(config, markers={"ids": [int(i) for i in plan.markers]}), plan


def evaluate_and_report(model, dataset, folder, *, renders: int = EvaluateConfig.renders, studies_folder=None,
                        title="tissuecast report", targets=None):
    """Evaluate on valid/test-1/test-2 and write the report; returns ``(evaluation, index.html path)``.

    ``targets``: where TRE is measured (:class:`~.targets.Targets`); default the targets of
    the config the model was trained with (:func:`~.targets.model_targets`).
    """
    from ..evaluate.evaluation import evaluate_model
    from ..evaluate.report import write_report
    from ..evaluate.targets import model_targets

    evaluation = evaluate_model(model, dataset, targets=targets if targets is not None else model_targets(model))
    index = write_report(folder, model, dataset, evaluation, renders=renders, studies_folder=studies_folder, title=title)
    return evaluation, index


def run_pipeline(config: Config, *, simulate: bool = True, progress: bool = True, workers: int | None = None) -> dict:
    """Simulate (resumable) -> train -> evaluate -> report, as ``config`` says.

    Returns:
        ``{"paths": RunPaths, "dataset": summary, "nominal_dataset": summary or None (``surrogate.nominal_expert``),
        "model": DeformationModel, "evaluation": Evaluation, "report": Path, "seconds": {stage: s}}``.

    Raises:
        ConfigError: a path of the config that does not name what its key reads
            (:func:`~tissuecast.app.configuration.check_config`), or a data set too small to train,
            validate and evaluate on (:func:`~tissuecast.app.configuration.check_run_sizes`), or a
            negative ``workers``, before anything runs.
    """
    from .configuration import check_config, check_run_sizes

    check_config(config)
    check_run_sizes(config)
    from ..dataset.generate import check_workers

    check_workers(workers)
    paths = run_paths(config)
    if config.surrogate.nominal_expert and not simulate and not paths.nominal_store.exists():
        raise ConfigError(f"surrogate.nominal_expert = true, but the nominal expert's store {paths.nominal_store} does "
                          "not exist; run without --skip-simulate (it simulates both stores)")
    paths.output.mkdir(parents=True, exist_ok=True)
    seconds = {}
    summary = nominal_summary = None
    if simulate:
        from ..dataset import simulate as simulate_store

        t = time.perf_counter()
        summary = simulate_store(config, paths.store, progress=progress, workers=workers)
        seconds["simulate"] = time.perf_counter() - t
        if config.surrogate.nominal_expert:
            from ..evaluate.mismatch import store_alpha

            t = time.perf_counter()
            nominal_summary = simulate_store(nominal_config(config, paths.nominal_store, store_alpha(paths.store)),
                                             paths.nominal_store, progress=progress, workers=workers)
            seconds["simulate nominal"] = time.perf_counter() - t
    t = time.perf_counter()
    expert = config.surrogate.nominal_expert
    model, ds = train_from_store(config, paths.store, model_folder=paths.model, onnx=not expert)  # a pair: its graph below
    if expert:
        model = add_nominal_expert(config, model, ds, paths.nominal_store, model_folder=paths.model)
    seconds["train"] = time.perf_counter() - t
    t = time.perf_counter()
    from ..evaluate.targets import model_targets

    evaluation, index = evaluate_and_report(model, ds, paths.report, renders=config.evaluate.renders,
                                            title=f"tissuecast: {config.name}", targets=model_targets(model, config))
    seconds["evaluate"] = time.perf_counter() - t
    return {"paths": paths, "dataset": summary, "nominal_dataset": nominal_summary, "model": model, "evaluation": evaluation,
            "report": index, "seconds": seconds}


def resolve_source(source=None, store=None) -> tuple[Config, Path]:
    """A CLI's ``CONFIG|STORE`` argument -> ``(config, store path)``.

    A directory is taken as a data-set store (its own config is used); a file as a TOML
    config whose ``dataset.store`` (or ``store``) is the store; None means the defaults.
    """
    from .configuration import load_run_config

    if source is not None and Path(source).is_dir():
        from ..dataset import open_dataset

        return open_dataset(source).config, Path(store or source)
    cfg = load_run_config(source)
    return cfg, Path(store or cfg.dataset.store)
