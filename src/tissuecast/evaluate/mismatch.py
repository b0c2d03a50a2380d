"""What a mismatch between the simulator and the patient costs: the mismatch study.

Every model is trained on one simulator. :func:`mismatch_study` simulates named test sets in
which one thing differs from the nominal scenario, as it may in the operating room, and
evaluates every given model on each, side by side: the learned model, rigid registration from
the markers and ridge (test-1 metrics of :mod:`.evaluation`), the error at the targets (TRE,
share of their displacement corrected), the 90 % bounds' coverage and the alarm's rate.

The sets (:func:`mismatch_sets`, those the scenario has the parts for):

* ``nominal`` -- the nominal parameters;
* ``E x0.5``, ``E x2``, ``E x4`` -- every element's Young's modulus scaled;
* ``nu 0.40``, ``nu 0.49`` -- Poisson's ratio;
* ``springs x0.25``, ``springs x4`` -- the elastic support's stiffness (normal and tangential);
* ``attached +5 mm``, ``attached -5 mm``, ``attached +10 mm`` -- the attached region grown or
  shrunk along the surface (:mod:`tissuecast.scenario.parameters`);
* ``gravity 45 deg off`` -- the surgery's gravity direction 45 degrees from the nominal one;
* ``inclusion 3x E`` -- a sphere of a third of the body's smallest extent at its centre, three
  times as stiff;
* ``quadratic elements`` (a data set of linear elements only) -- the nominal samples solved
  again with quadratic elements on the same mesh: the element order's share of the truth's
  own discretisation error (a lower bound of the whole);
* ``discretisation`` -- the nominal samples solved again on the uniformly refined mesh with
  quadratic elements (:mod:`tissuecast.scenario.refined`), read on the model's vertices: the
  truth's discretisation error against a finer reference. Its solves take far longer than a
  data set's (docs/uncertainty.md), so it runs only when named (``sets``); every other set runs
  by default.

A set is a data set (:func:`tissuecast.dataset.simulate`, resumable) of the config with no
uncertain parameter drawn but the set's one fixed, every sample in test-1, the force
magnitude fixed to ``alpha`` (the training store's calibrated one: the same loads), the
model's markers and fixed vertices, and a study seed of its own (so no set shares a sample
with the training data, and every set shares its samples' loads with the others). A set is
*in range* when the config's ``[scenario.uncertain]`` ranges (or its gravity cone) cover its
value: a model trained with them has seen such data.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config, nothing_drawn, with_overrides
from ..errors import ConfigError, ConvergenceError

__all__ = ["MismatchSet", "mismatch_sets", "chosen_sets", "set_config", "ArraySet", "ReferenceSolver",
           "along_load_path", "keep_answers_of_one_path", "solve_path", "discretisation_set", "evaluate_on_set",
           "set_folder_name", "store_alpha", "mismatch_study", "PhysicsRows", "physics_on_set", "set_margins", "PHYSICS",
           "PHYSICS_KNOWN", "DEFAULT_SAMPLES",
           "DISCRETISATION_SAMPLES", "REFINED_TIME_LIMIT", "STUDY_SEED_OFFSET"]

log = logging.getLogger(__name__)

#: Samples per set by default, and of each (costly) set solved again with quadratic elements.
DEFAULT_SAMPLES = 100
#: The model label of the physics inverse's rows (``mismatch_study(physics=PhysicsRows(...))``),
#: and of its rows with each frame's attached margin given (``PhysicsRows.known_margin``).
PHYSICS = "physics"
PHYSICS_KNOWN = "physics, margin known"
DISCRETISATION_SAMPLES = 4
#: Wall-clock limit of one solve of those sets by default, s.
REFINED_TIME_LIMIT = 900.0
#: The sets' data-set seed is the config's plus this.
STUDY_SEED_OFFSET = 7919


@dataclass(frozen=True)
class MismatchSet:
    """One perturbed test set.

    Attributes:
        name: e.g. ``"E x0.5"``.
        what: one line saying what differs.
        uncertain: ``[scenario.uncertain]`` fixed values of the set (``{name: [v, v]}``).
        scenario: other ``[scenario]`` overrides (gravity direction, an inclusion).
        in_range: whether the config's uncertain ranges cover it (None for the nominal set).
        reference: ``""`` for a simulated set; ``"p2"`` or ``"refined"`` for the nominal samples
            solved again (:class:`ReferenceSolver`).
        default: whether the study runs it when no set is named.
    """

    name: str
    what: str
    uncertain: dict = dataclasses.field(default_factory=dict)
    scenario: dict = dataclasses.field(default_factory=dict)
    in_range: bool | None = None
    reference: str = ""
    default: bool = True


def _covers(bounds: tuple, value: float) -> bool:
    return bool(bounds) and float(bounds[0]) - 1e-12 <= value <= float(bounds[1]) + 1e-12


def _rotated(direction, degrees: float) -> list[float]:
    """``direction`` turned by ``degrees`` about an axis normal to it."""
    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]
    axis = np.cross(d, helper)
    axis /= np.linalg.norm(axis)
    t = np.radians(degrees)
    return (np.cos(t) * d + np.sin(t) * np.cross(axis, d)).tolist()


def _inclusion(mesh) -> dict:
    """A sphere at the body's centre of a third of its smallest extent, 3x as stiff (overrides
    filled in by :func:`mismatch_sets` with E)."""
    centre = np.asarray(mesh.points, dtype=np.float64).mean(axis=0)
    return {"name": "inclusion", "rule": "distance", "point": centre.tolist(), "distance": float(min(mesh.extent)) / 3.0}


def mismatch_sets(config: Config, mesh) -> list[MismatchSet]:
    """The sets (module notes) the scenario of ``config`` has the parts for, nominal first."""
    sc, u = config.scenario, config.scenario.uncertain
    out = [MismatchSet("nominal", "the nominal parameters")]
    for f in (0.5, 2.0, 4.0):
        out.append(MismatchSet(f"E x{f:g}", f"Young's modulus x{f:g} everywhere", {"youngs_modulus": [f, f]},
                               in_range=_covers(u.youngs_modulus, f)))
    for nu in (0.40, 0.49):
        out.append(MismatchSet(f"nu {nu:.2f}", f"Poisson's ratio {nu:.2f}", {"poisson_ratio": [nu, nu]},
                               in_range=_covers(u.poisson_ratio, nu)))
    if sc.springs.rule != "none":
        for f in (0.25, 4.0):
            out.append(MismatchSet(f"springs x{f:g}", f"the surroundings' stiffness x{f:g}",
                                   {"spring_normal": [f, f], "spring_tangential": [f, f]},
                                   in_range=_covers(u.spring_normal, f) and _covers(u.spring_tangential, f)))
    if sc.attached.rule != "none":
        for m in (5.0, -5.0, 10.0):
            out.append(MismatchSet(f"attached {m:+g} mm", f"the attached region {'grown' if m > 0 else 'shrunk'} by "
                                   f"{abs(m):g} mm along the surface", {"attached_margin": [m, m]},
                                   in_range=_covers(u.attached_margin, m)))
    if sc.gravity.enabled:
        out.append(MismatchSet("gravity 45 deg off", "gravity during surgery 45 degrees from the nominal direction",
                               scenario={"gravity": {"surgery_direction": _rotated(sc.gravity.surgery_direction, 45.0),
                                                     "cone_angle": 0.0}},
                               in_range=sc.gravity.cone_angle >= 45.0))
    regions = [dataclasses.asdict(r) for r in sc.materials.regions]
    inclusion = {**_inclusion(mesh), "youngs_modulus": 3.0 * config.material.youngs_modulus,
                 "poisson_ratio": config.material.poisson_ratio}
    out.append(MismatchSet("inclusion 3x E", "a stiffer inclusion (3x E) at the body's centre",
                           scenario={"materials": {"regions": regions + [inclusion]}}, in_range=False))
    if config.solver.order == 1:
        out.append(MismatchSet("quadratic elements", "the nominal samples with quadratic elements on the same mesh",
                               reference="p2", in_range=None))
    out.append(MismatchSet("discretisation", "the nominal samples on the refined mesh, quadratic elements",
                           reference="refined", in_range=None, default=False))
    return out


def chosen_sets(config: Config, mesh, names=None) -> list[MismatchSet]:
    """The sets a study runs: ``names`` (and the nominal set, which every relative figure
    needs), or by default those of :func:`mismatch_sets` marked ``default``.

    Raises:
        ConfigError: a name that is not a set of this scenario (the error lists them).
    """
    every = mismatch_sets(config, mesh)
    if not names:
        return [s for s in every if s.default]
    unknown = set(names) - {s.name for s in every}
    if unknown:
        raise ConfigError(f"unknown mismatch set(s) {sorted(unknown)}; choose among {[s.name for s in every]}")
    return [s for s in every if s.name in names or s.name == "nominal"]


def set_config(config: Config, mset: MismatchSet, *, alpha: float, samples: int, markers, fixed, store) -> Config:
    """The data-set config of one set (module notes)."""
    # every sample of a set has the set's values: no share of them falls back to the nominal ones
    scenario = {"uncertain": {**nothing_drawn(), **mset.uncertain}, **mset.scenario}
    ds = {"store": str(store), "n_samples": samples, "n_test2": 0, "split": [0.0, 0.0, 1.0], "alpha": float(alpha),
          "seed": config.dataset.seed + STUDY_SEED_OFFSET, "predictor_samples": max(2, min(24, samples // 4))}
    mk = {"ids": [int(i) for i in markers]}
    if config.scenario.pins:
        mk["fixed_ids"] = [int(i) for i in fixed]
    return with_overrides(config, scenario=scenario, dataset=ds, markers=mk)


class ArraySet:
    """Fields given as arrays, read like a data set's test-1 (what :func:`.evaluation.evaluate_model` needs).

    Args:
        displacements: (N, n, 3) float mm.
        mesh: the mesh.
        record: the scenario's record (dict), or None when not known.
        instrument_poses: the samples' instrument poses (as :attr:`~tissuecast.dataset.Dataset.instrument_poses`).
        parameters: the samples' drawn parameters (as :attr:`~tissuecast.dataset.Dataset.parameters`).
    """

    def __init__(self, displacements: np.ndarray, mesh, record: dict | None, instrument_poses: dict | None = None,
                 parameters: dict | None = None):
        self.displacements = np.asarray(displacements)
        self.mesh = mesh
        self.scenario = record
        self.beta = np.full(len(self.displacements), np.nan)
        self.n_samples = len(self.displacements)
        self.instrument_poses = instrument_poses or {}
        self.parameters = parameters or {}

    @classmethod
    def of_samples(cls, dataset, samples, displacements: np.ndarray) -> "ArraySet":
        """Other fields of ``dataset``'s samples ``samples`` ((k,) ids; e.g. solved again on a
        finer mesh), with the data set's mesh and scenario record and those samples' instrument
        poses and parameters; ``displacements`` (k, n, 3) float mm."""
        kept = np.asarray(samples, dtype=np.int64)
        poses = {name: {part: v[kept] for part, v in pose.items()} for name, pose in dataset.instrument_poses.items()}
        return cls(np.asarray(displacements).reshape(len(kept), dataset.mesh.n_vertices, 3), dataset.mesh,
                   dataset.scenario, poses, {name: v[kept] for name, v in dataset.parameters.items()})

    def select(self, split=None, status: str | None = "done") -> np.ndarray:
        """Every sample is test-1 and done."""
        return np.arange(len(self.displacements)) if split in (None, "test1") else np.zeros(0, dtype=np.int64)


def along_load_path(config: Config) -> bool:
    """Whether a data set of ``config`` is solved from zero along the load path (no initial guess)."""
    return config.dataset.predictor == "none"


def solve_path(config: Config) -> str:
    """How the references of a data set of ``config`` are solved (:class:`ReferenceSolver`), as
    recorded beside their answers (:func:`keep_answers_of_one_path`)."""
    return "load path" if along_load_path(config) else "from the data set's answer"


class ReferenceSolver:
    """Solves a data set's samples again with quadratic elements, read on its vertices.

    Args:
        dataset: the data set (its mesh, config, scenario arrays, seeds, alphas and fields).
        kind: ``"refined"`` (the uniformly refined mesh, :mod:`tissuecast.scenario.refined`) or
            ``"p2"`` (the data set's own mesh: the element order's share of the error alone).

    Each solve takes the data set's solve path with the data set's solver settings: from zero
    along the load path when the data set is solved so (``dataset.predictor = "none"``: a body
    with more than one equilibrium under the same loads gets the one its loading reaches, as the
    data set's own answer is), otherwise from the data set's answer at the full load.
    """

    def __init__(self, dataset, kind: str):
        from ..scenario import restore_scenario

        if kind not in ("refined", "p2"):
            raise ValueError(f"kind must be 'refined' or 'p2', got {kind!r}")
        self.dataset, self.kind = dataset, kind
        cfg = dataset.config
        self.solver_config = dataclasses.replace(cfg.solver, order=2)
        if kind == "refined":
            from ..mesh.refine import refine_uniformly

            self.scenario = restore_scenario(dataset.mesh, cfg, dataset.scenario_arrays, dataset.basis)
            self.refined = refine_uniformly(dataset.mesh)
        else:
            self.scenario = restore_scenario(dataset.mesh, with_overrides(cfg, solver={"order": 2}),
                                             dataset.scenario_arrays, dataset.basis)
            self.refined = None

    @property
    def along_load_path(self) -> bool:
        """Whether each solve starts from zero along the load path (the data set's own path)."""
        return along_load_path(self.dataset.config)

    @property
    def n_vertices(self) -> int:
        """Vertices of the mesh the reference is solved on."""
        return (self.dataset.mesh if self.refined is None else self.refined.mesh).n_vertices

    def solve(self, k: int, *, time_limit: float | None = None) -> np.ndarray:
        """Sample ``k``'s answer (n, 3) float64 mm on the data set's n vertices. A solve that stops
        is tried again more cautiously, as the data set's own samples are (``solver.retries``
        times: exact Newton steps, smaller increments; :func:`~tissuecast.dataset.worker.retry_solver_config`),
        from the state it reached (the load path kept up to there), all attempts within
        ``time_limit`` s together.

        Raises:
            ConvergenceError: no attempt converges (the last one's); SolveTimeout (one) past ``time_limit`` s.
        """
        from ..dataset.worker import retry_solver_config
        from ..errors import ConvergenceError, SolveTimeout

        ds = self.dataset
        inputs = self.scenario.sample(int(ds.seed[k]), float(ds.alpha[k]))
        data = None if self.along_load_path else np.asarray(ds.displacements[k], dtype=np.float64)
        reached = None  # every node's displacement where the last attempt stopped
        start, attempts = time.perf_counter(), ds.config.solver.retries + 1
        for attempt in range(attempts):
            left = time_limit if time_limit is None or attempt == 0 else time_limit - (time.perf_counter() - start)
            if left is not None and left <= 0:
                raise SolveTimeout(f"sample {k}: {attempt} attempt(s) used the time limit of {time_limit:g} s",
                                   time.perf_counter() - start, time_limit)
            try:
                return self._solve_once(inputs, retry_solver_config(self.solver_config, attempt), left, data, reached)
            except SolveTimeout:
                raise
            except ConvergenceError as exc:
                if attempt + 1 == attempts:
                    raise
                if exc.result is not None and exc.load_fraction > 0:
                    reached = exc.result.nodal_displacement
                log.info("reference of sample %d: attempt %d of %d stopped at %.1f %% of its load (%s); trying again "
                         "with exact Newton steps and smaller increments%s", k, attempt + 1, attempts,
                         100 * exc.load_fraction, exc, "" if reached is None else ", from where it stopped")

    def _solve_once(self, inputs, solver_config, time_limit, data, reached) -> np.ndarray:
        """One solve of a sample's ``inputs`` with ``solver_config``: from ``reached`` (every node's
        displacement, where an earlier attempt stopped), else from ``data`` (the data set's answer
        on its vertices), else from zero."""
        from ..fem import Solver
        from ..scenario.refined import refined_sample

        ds = self.dataset
        if self.refined is not None:
            fine = refined_sample(self.scenario, ds.config, self.refined, inputs)
            guess = reached if reached is not None else None if data is None else self.refined.from_coarse(data)
            res = Solver(fine.problem, solver_config).solve(fine.surface, initial_guess=guess, time_limit=time_limit,
                                                            **fine.keywords)
            return self.refined.coarse_values(res.displacement)
        problem = self.scenario.problem()
        changes = {key: v for key, v in zip(("materials", "springs"), inputs.solver_parameters) if v is not None}
        problem = dataclasses.replace(problem, **changes) if changes else problem
        res = Solver(problem, solver_config).solve(inputs.surface, initial_guess=reached if reached is not None else data,
                                                   time_limit=time_limit, **inputs.solve_keywords())
        return np.asarray(res.displacement[: ds.mesh.n_vertices])


def discretisation_set(config: Config, nominal_store, folder: Path, samples: int, *, reference: str = "refined",
                       time_limit: float | None = REFINED_TIME_LIMIT) -> ArraySet:
    """The first ``samples`` samples of the nominal set solved again with quadratic elements
    (:class:`ReferenceSolver`, ``reference`` ``"refined"`` or ``"p2"``), read on the coarse
    vertices, with their instrument poses and parameters: an :class:`ArraySet` of k <=
    ``samples`` fields. Each is saved in ``folder`` as it comes and reused when the study is run
    again.

    A solve that does not converge, or runs past ``time_limit`` s (None: no limit), is left
    out, logged and recorded in ``folder`` (``sample_NNNNN.failed.json``: why, how long it ran,
    the limit): a second run does not try it again unless its limit is larger than the recorded
    one (or the record is deleted). ``folder/reference.json`` records how the answers are solved
    (the reference and the solve path, :class:`ReferenceSolver`); answers solved otherwise are
    moved to ``folder/superseded/`` and solved again."""
    from ..dataset import open_dataset
    from ..errors import ConvergenceError, SolveTimeout

    ds = open_dataset(nominal_store)
    folder.mkdir(parents=True, exist_ok=True)
    keep_answers_of_one_path(folder, {"reference": reference, "path": solve_path(ds.config)})
    limit = float("inf") if time_limit is None else float(time_limit)
    chosen = [int(k) for k in ds.select("test1", status="done")[:samples]]
    todo = [k for k in chosen if not _refined_file(folder, k).is_file() and _retry_refined(folder, k, limit)]
    where = "on the refined mesh" if reference == "refined" else "with quadratic elements on the same mesh"
    if todo:  # the reference's problem is built only when there is something to solve
        solver = ReferenceSolver(ds, reference)
        log.info("discretisation: solving %d nominal samples again %s (%d vertices, quadratic elements; each can take "
                 "minutes, at most %s), saved in %s as they come", len(todo), where, solver.n_vertices,
                 "no limit" if time_limit is None else f"{limit:.0f} s", folder)
    spent = 0.0
    for done, k in enumerate(todo, start=1):
        t0 = time.perf_counter()
        try:
            field = solver.solve(k, time_limit=time_limit)
        except ConvergenceError as exc:
            seconds = time.perf_counter() - t0
            why = "ran past its time limit" if isinstance(exc, SolveTimeout) else "did not converge"
            record = _refined_file(folder, k, failed=True)
            record.write_text(json.dumps({"sample": k, "reason": str(exc), "timeout": isinstance(exc, SolveTimeout),
                                          "seconds": seconds, "time_limit": time_limit}, indent=1) + "\n")
            again = ("a larger --refined-time-limit tries it again" if isinstance(exc, SolveTimeout)
                     else "not tried again unless the record is deleted")
            log.warning("discretisation: sample %d %s %s (%s); left out and recorded in %s (%s)", k, why, where, exc,
                        record, again)
        else:
            np.save(_refined_file(folder, k), field)
            seconds = time.perf_counter() - t0
            log.info("discretisation: sample %d solved %s in %.0f s", k, where, seconds)
        spent += seconds
        log.info("discretisation: %d of %d tried; about %.0f min left (--refined-samples sets how many, "
                 "--sets can leave the set out)", done, len(todo), (len(todo) - done) * spent / done / 60.0)
    kept = [k for k in chosen if _refined_file(folder, k).is_file()]
    return ArraySet.of_samples(ds, kept, [np.load(_refined_file(folder, k)) for k in kept])


#: Where a set's folder records how its answers were solved (:func:`discretisation_set`).
REFERENCE_RECORD = "reference.json"


def keep_answers_of_one_path(folder: Path, how: dict) -> None:
    """Record ``how`` the reference answers in ``folder`` (``sample_*.npy``, ``sample_*.failed.json``)
    are solved (JSON-able, e.g. ``{"reference": "p2", "path": "load path"}``); answers solved
    otherwise (or by a version that did not record it) are moved to ``folder/superseded/`` and
    logged, so that a folder never mixes two references."""
    record = folder / REFERENCE_RECORD
    earlier = json.loads(record.read_text()) if record.is_file() else None
    old = sorted(folder.glob("sample_*.npy")) + sorted(folder.glob("sample_*.failed.json"))
    if earlier != how and old:
        aside = folder / "superseded"
        aside.mkdir(exist_ok=True)
        for path in old:
            path.replace(aside / path.name)
        log.warning("discretisation: the %d answers in %s were solved %s, not %s: they are moved to %s and solved "
                    "again", len(old), folder, "by a version that did not record how" if earlier is None
                    else json.dumps(earlier), json.dumps(how), aside)
    record.write_text(json.dumps(how, indent=1) + "\n")


def _refined_file(folder: Path, k: int, *, failed: bool = False) -> Path:
    """Where sample ``k``'s refined answer is saved (``.npy``), or its failure recorded (``.failed.json``)."""
    return folder / f"sample_{k:05d}{'.failed.json' if failed else '.npy'}"


def _retry_refined(folder: Path, k: int, limit: float) -> bool:
    """Whether sample ``k``'s refined solve is to be tried: no failure recorded, or a time-out
    under a smaller limit than ``limit`` s."""
    record = _refined_file(folder, k, failed=True)
    if not record.is_file():
        return True
    doc = json.loads(record.read_text())
    before = float("inf") if doc.get("time_limit") is None else float(doc["time_limit"])
    return bool(doc.get("timeout")) and limit > before


def evaluate_on_set(model, dataset, targets) -> dict:
    """One model on one set: the test-1 figures of :func:`.evaluation.evaluate_model` (learned
    model, rigid, ridge, TRE) and, with a trust layer, the 90 % bounds' coverage and the alarm's rate."""
    from .evaluation import evaluate_model
    from .headline import ALARM_REASONS
    from .trust_report import bound_figures

    result = evaluate_model(model, dataset, splits=("test1",), targets=targets).sets["test1"]
    row = {"count": int(result.indices.size), "peak_median": float(np.median(result.max_displacement)),
           "nonrigid_median": float(np.median(result.nonrigid)), "gate_refused": result.refused_share}
    for m in ("mlp", "rigid", "ridge"):
        s = result.summary(m)
        row[f"{m}_offset_max"] = float(s.offset_max)
        row[f"{m}_offset_mean"] = float(s.offset_mean)
        t = result.target_summary(m)
        if t is not None:
            row[f"{m}_tre_mean"] = float(t.tre_mean)
            row[f"{m}_tre_p95"] = float(t.tre_p95)
            row[f"{m}_corrected"] = float(t.share_corrected_mean)
    row["relative"] = row["mlp_offset_max"] / max(row["peak_median"], 1e-300)
    row["gain_over_rigid"] = row["rigid_offset_max"] / max(row["mlp_offset_max"], 1e-300)
    if model.has_trust:
        from .evaluation import auxiliary_values

        idx = dataset.select("test1", status="done")
        aux = auxiliary_values(model, dataset)
        with model.gate_suspended():
            figures = bound_figures(model.bounds_predictor, np.asarray(dataset.displacements[idx], dtype=np.float64),
                                    levels=(0.9,), auxiliary=None if aux is None else aux[idx])
        row["coverage_90"] = figures["coverage_0.9"]
        row["alarm_rate"] = figures["alarm_rate"] if figures["alarm_on"] else float("nan")
        if figures["alarm_on"]:  # what the user sees: a refusal (the gate) or an alarm
            row["flagged_rate"] = float(np.mean(result.refused | figures["alarms"]))
            row.update({key: figures[key] for key in ALARM_REASONS})
    return row


def physics_on_set(inverse, model, dataset, targets, samples: int, *, time_limit: float | None = None,
                   known_margin: bool = False, estimate: str | None = None) -> dict:
    """The physics inverse on a set's first ``samples`` test-1 samples, as a study row.

    Each frame is solved as ``tissuecast predict --physics`` solves it: the model's markers (all
    tracked, no noise), the sample's recorded instrument poses, gravity in its planned direction,
    ``inverse`` (a :class:`~tissuecast.inverse.MarkerInverse` of the training store's simulator:
    what the model assumes), ``time_limit`` s a frame (None: none). ``known_margin``: each frame
    is given the attached margin its sample was simulated with (0 where the set draws none: the
    nominal extent), as ``predict --physics --attached-margin`` a measured one; the margin must
    lie within the inverse's :attr:`~tissuecast.inverse.MarkerInverse.margin_range`.
    ``estimate``: the field of a searched frame (:data:`~tissuecast.inverse.ESTIMATES`; None:
    the default one).

    Returns:
        The keys of :func:`evaluate_on_set` over those samples (no input gate's share: the frames
        are solved whatever the model's gate says), the inverse's figures in the
        ``mlp_*`` keys (rigid registration and ridge from the same markers on the same samples),
        ``coverage_90`` the share of vertices within its 90 % band
        (:func:`~tissuecast.inverse.spread_band`), ``alarm_rate`` the share of frames whose fit
        the misfit warning flags (:meth:`~tissuecast.inverse.MarkerInverse.flags`),
        ``seconds_median`` a frame's median time, ``incomplete`` how many frames the limit cut short,
        ``failed`` how many frames had no equilibrium to start from (logged, left out of the
        figures; all of them: ``count`` 0 and NaN figures).
    """
    from ..fem.linear import one_blas_thread
    from ..instruments import recorded_poses
    from ..registration import nonrigid_part
    from .metrics import summarize_targets, target_errors

    idx = physics_frames(dataset, samples)
    U = np.asarray(dataset.displacements[idx], dtype=np.float64)
    d = U[:, model.markers]
    margins = set_margins(dataset, idx) if known_margin else [None] * idx.size
    fields, covered, flagged, seconds, cut, solved = [], [], [], [], 0, []
    for k, s in enumerate(idx):
        draw = inverse.scenario.frame_draw(recorded_poses(dataset.instrument_poses, int(s)))
        try:
            with one_blas_thread():
                res = inverse.solve(d[k], draw, time_limit=time_limit, attached_margin=margins[k], estimate=estimate)
        except ConvergenceError as e:  # recorded in the row, left out of its figures
            log.warning("physics frame %d of %d (sample %d) not solved: %s", k + 1, idx.size, int(s), e)
            continue
        solved.append(k)
        fields.append(res.field)
        covered.append(res.within_band(U[k]))
        flagged.append(inverse.flags(res))
        seconds.append(res.seconds)
        cut += not res.complete
        log.info("physics frame %d of %d: worst vertex %.3g mm off, markers fitted to %.3g mm, %.0f s%s", k + 1,
                 idx.size, float(np.linalg.norm(res.field - U[k], axis=1).max()), res.marker_misfit, res.seconds,
                 "" if res.complete else " (cut short by the time limit)")
    failed = int(idx.size - len(solved))
    if not solved:
        keys = ["peak_median", "nonrigid_median", "relative", "gain_over_rigid", "coverage_90", "alarm_rate",
                "seconds_median"] + [f"{m}_{k}" for m in ("mlp", "rigid", "ridge")
                                     for k in ("offset_max", "offset_mean", "tre_mean", "tre_p95", "corrected")]
        return {"count": 0, "failed": failed, "incomplete": 0, **dict.fromkeys(keys, float("nan"))}
    U, d = U[solved], d[solved]
    row = {"count": len(solved), "failed": failed,
           "peak_median": float(np.median(np.linalg.norm(U, axis=2).max(axis=1))),
           "nonrigid_median": float(np.median(nonrigid_part(dataset.mesh.points, U)))}
    moved = np.linalg.norm(targets.displacements(U), axis=2).mean(axis=1)
    for m, F in (("mlp", np.stack(fields)), ("rigid", model.predict_rigid(d)), ("ridge", model.predict_ridge(d))):
        e = np.linalg.norm(F - U, axis=2)
        row[f"{m}_offset_max"], row[f"{m}_offset_mean"] = float(e.max(axis=1).mean()), float(e.mean())
        t = summarize_targets(target_errors(targets.displacements(F), targets.displacements(U)), moved)
        row[f"{m}_tre_mean"], row[f"{m}_tre_p95"], row[f"{m}_corrected"] = t.tre_mean, t.tre_p95, t.share_corrected_mean
    row["relative"] = row["mlp_offset_max"] / max(row["peak_median"], 1e-300)
    row["gain_over_rigid"] = row["rigid_offset_max"] / max(row["mlp_offset_max"], 1e-300)
    row.update(coverage_90=float(np.mean(covered)), alarm_rate=float(np.mean(flagged)),
               seconds_median=float(np.median(seconds)), incomplete=cut)
    return row


def physics_frames(dataset, samples: int) -> np.ndarray:
    """(k,) int64, the sample ids of a set's first ``samples`` solved test-1 samples (the
    physics rows' frames)."""
    return np.asarray(dataset.select("test1", status="done"), dtype=np.int64)[:samples]


def set_margins(dataset, idx) -> np.ndarray:
    """(len(idx),) mm: the attached margin each of the samples ``idx`` was simulated with (0
    where the set records none: the nominal extent)."""
    recorded = dataset.parameters.get("attached_margin")
    if recorded is None:
        return np.zeros(len(idx))
    return np.asarray(recorded, dtype=np.float64)[np.asarray(idx, dtype=np.int64)]


def store_alpha(store) -> float:
    """The calibrated force magnitude alpha (N) of a training store."""
    from ..dataset import open_dataset

    cal = open_dataset(store).calibration or {}
    return float(cal.get("alpha", 0.0))


def _set_dataset(config: Config, mset: MismatchSet, folder: Path, *, alpha, samples, model, progress, nominal_store,
                 refined_time_limit):
    """The set's samples as a data set (simulated, or resumed, in ``folder``) or, for the
    discretisation set, as an :class:`ArraySet`; None when it has no sample."""
    from ..dataset import open_dataset, simulate

    if mset.reference:
        fields = discretisation_set(config, nominal_store, folder / set_folder_name(mset.name), samples,
                                    reference=mset.reference, time_limit=refined_time_limit)
        return fields if fields.n_samples else None
    store = folder / f"{set_folder_name(mset.name)}.zarr"
    cfg = set_config(config, mset, alpha=alpha, samples=samples, markers=model.markers, fixed=model.fixed, store=store)
    simulate(cfg, store, progress=progress)
    return open_dataset(store)


def set_folder_name(name: str) -> str:
    """A set's store folder name: ``"attached +5 mm"`` -> ``"attached_plus5_mm"`` (signs and
    decimal points spelled out, so that no two sets share a folder)."""
    spelled = name.replace("+", "plus").replace("-", "minus").replace(".", "p")
    return "".join(c if c.isalnum() else "_" for c in spelled).strip("_").lower()


@dataclass(frozen=True)
class PhysicsRows:
    """The study's rows of the physics inverse (:func:`physics_on_set`).

    Attributes:
        frames: each set's first ``frames`` test-1 frames solved (a row labelled
            :data:`PHYSICS`; the first model's markers and training store's simulator, its ranges
            as priors); each takes seconds to minutes.
        time_limit: seconds one frame may take (None: none).
        known_margin: the same frames also with each one's attached margin given
            (``physics_on_set(known_margin=True)``, a row labelled :data:`PHYSICS_KNOWN`; what a
            measured attachment is worth), on every set whose margins lie within the training
            store's range (a set beyond it is left out of these rows, and logged).
        estimate: the field where the margin is searched (:data:`~tissuecast.inverse.ESTIMATES`;
            None: the default one).
    """

    frames: int
    time_limit: float | None = None
    known_margin: bool = False
    estimate: str | None = None


def mismatch_study(config: Config, models: dict, folder, *, alpha: float, sets=None, samples: int = DEFAULT_SAMPLES,
                   refined_samples: int = DISCRETISATION_SAMPLES, refined_time_limit: float | None = REFINED_TIME_LIMIT,
                   targets=None, progress: bool = False, on_row=None, physics: PhysicsRows | None = None) -> list[dict]:
    """Simulate the mismatch sets and evaluate every model on each (module notes).

    Args:
        config: the scenario's config (its ``[scenario.uncertain]`` ranges say what is in range).
        models: ``{label: DeformationModel}`` (e.g. ``{"nominal": ..., "uncertain": ...}``), all on
            the config's mesh with the same markers.
        folder: where the sets' stores are kept (resumed when the study is run again).
        alpha: the force magnitude of every set, N.
        sets: names of the sets to run (default: those of :func:`mismatch_sets` marked ``default``,
            every one but the refined ``discretisation``).
        samples: samples per set; ``refined_samples`` of each set solved again with quadratic elements.
        refined_time_limit: wall-clock limit of one solve of those sets, s (None: none); a sample
            past it is left out (:func:`discretisation_set`).
        targets: where TRE is measured (default: the evaluation's interior rule).
        progress: progress bars of the simulations.
        on_row: called with each row as it comes.
        physics: the physics inverse's rows (:class:`PhysicsRows`), or None (none).

    Returns:
        One row per (set, model): the figures of :func:`evaluate_on_set` with ``set``, ``what``,
        ``in_range``, ``model`` and ``relative_vs_nominal`` (the relative error over that
        model's own on the nominal set).
    """
    folder = Path(folder)
    first = next(iter(models.values()))
    chosen = chosen_sets(config, first.mesh, sets)
    inverse = None
    physics = physics or PhysicsRows(0)
    if physics.frames > 0:
        from ..dataset import open_dataset
        from ..inverse import MarkerInverse
        from .targets import interior_targets

        for label in (PHYSICS, PHYSICS_KNOWN):
            if label in models:
                raise ConfigError(f"a model is labelled {label!r}, the label of the physics rows; give it another label")
        if not first.dataset_path or not Path(first.dataset_path).exists():
            raise ConfigError(f"the physics rows solve with the first model's training store, which is not at "
                              f"{first.dataset_path!r}; put it back (or leave the physics rows out)")
        inverse = MarkerInverse.from_dataset(open_dataset(first.dataset_path), first.markers)
        if physics.known_margin and inverse.margin_range is None:
            raise ConfigError("the first model's training store does not draw the attached region's margin "
                              "([scenario.uncertain] attached_margin): there is no margin to give; leave the known-margin "
                              "rows out")
    elif physics.known_margin:
        raise ConfigError("the known-margin physics rows solve the physics rows' frames: give a number of physics frames")
    elif physics.estimate is not None:
        raise ConfigError("the estimate chooses the physics rows' field: give a number of physics frames")
    rows, nominal_relative = [], {}

    def add(mset: MismatchSet, label: str, figures: dict) -> None:
        row = {"set": mset.name, "what": mset.what, "in_range": mset.in_range, "model": label, **figures}
        if mset.name == "nominal":
            nominal_relative[label] = row["relative"]
        row["relative_vs_nominal"] = row["relative"] / nominal_relative.get(label, float("nan"))
        rows.append(row)
        if on_row is not None:
            on_row(row)

    nominal_store = folder / "nominal.zarr"
    for mset in chosen:
        ds = _set_dataset(config, mset, folder, alpha=alpha, samples=refined_samples if mset.reference else samples,
                          model=first, progress=progress, nominal_store=nominal_store,
                          refined_time_limit=refined_time_limit)
        if ds is None:
            continue
        for label, model in models.items():
            add(mset, label, evaluate_on_set(model, ds, targets))
        if inverse is not None:
            log.info("%s: the physics inverse on %d frames (seconds to minutes each)", mset.name, physics.frames)
            at = targets or interior_targets(first.mesh, exclude=first.fixed)
            add(mset, PHYSICS, physics_on_set(inverse, first, ds, at, physics.frames, time_limit=physics.time_limit,
                                              estimate=physics.estimate))
            if physics.known_margin:
                lo, hi = inverse.margin_range
                m = set_margins(ds, physics_frames(ds, physics.frames))
                if m.size and (m.min() < lo or m.max() > hi):
                    log.warning("%s: its attached margins (%+.3g to %+.3g mm) lie outside the training store's range "
                                "[%g, %g] mm; no known-margin physics row", mset.name, m.min(), m.max(), lo, hi)
                else:
                    add(mset, PHYSICS_KNOWN, physics_on_set(inverse, first, ds, at, physics.frames,
                                                            time_limit=physics.time_limit, known_margin=True))
    return rows
