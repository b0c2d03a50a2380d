"""Read-only access to a data-set store (see :mod:`.schema` for the layout), including the
:class:`~.worker.Recipe` its samples are solved with (:func:`recipe_from_store`)."""

from __future__ import annotations

import tomllib
from functools import cached_property
from pathlib import Path

import numpy as np

from ..config import Config, config_from_dict
from ..errors import DatasetError
from .sample_plan import SPLIT_CODES, SPLIT_NAMES
from .codes import STATUS_NAMES, InitialGuess, SampleStatus
from .schema import (DRAWS, INSTRUMENT_PREFIX, PARAMETERS, POSE_PARTS, check_schema, open_store_root, read_lbo_basis,
                     read_scenario_arrays)
from .store import StoreWriter
from .worker import Recipe

__all__ = ["Dataset", "open_dataset", "recipe_from_store", "max_displacement_stats"]

_STATUS_CODES = {v: k for k, v in STATUS_NAMES.items()}
#: ``summary()["predictor"]`` key of each initial-guess code
_PREDICTOR_KEYS = {InitialGuess.ZERO: "from_zero", InitialGuess.REDUCED_MODEL: "predicted",
                   InitialGuess.GUESS_FAILED: "prediction_failed", InitialGuess.PREVIOUS_ROUND: "from_previous_round",
                   InitialGuess.INTERIM_MODEL: "from_interim_model", InitialGuess.LINEAR_ANSWER: "from_linear_answer"}


def open_dataset(path) -> "Dataset":
    """Open a data-set store read-only.

    Raises:
        DatasetError: the path is missing, not a Zarr store, not a tissuecast data set, or
            of a newer schema version than this tissuecast reads.
    """
    path = Path(path)
    root = open_store_root(path, mode="r")
    check_schema(root, path)
    return Dataset(path, root)


def recipe_from_store(store, solver_factory: str | None = None) -> Recipe:
    """Everything a worker needs to solve a stored data set's samples exactly as its run did.

    Args:
        store: the store's path (opened read-only), or an open :class:`~.store.StoreWriter`.
        solver_factory: ``"module:function"`` replacing the FEM solver factory (for testing).

    Returns:
        The data set's :meth:`Dataset.recipe`; with :class:`~.worker.Task` and
        :func:`~.worker.solve_task` a sample (or a variant of it, e.g. another force
        magnitude) is solved in this process.
    """
    ds = Dataset(store.path, store.root) if isinstance(store, StoreWriter) else open_dataset(store)
    return ds.recipe(solver_factory)


def max_displacement_stats(values: np.ndarray) -> dict:
    """Distribution of per-sample maximum displacements (mm): min, quantiles, max, mean."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {}
    q = np.quantile(v, [0.05, 0.25, 0.5, 0.75, 0.9, 0.95])
    return {"count": int(len(v)), "min": float(v.min()), "p05": float(q[0]), "p25": float(q[1]),
            "median": float(q[2]), "p75": float(q[3]), "p90": float(q[4]), "p95": float(q[5]),
            "max": float(v.max()), "mean": float(v.mean())}


class Dataset:
    """A data set of FEM samples (read-only; arrays are loaded on first access).

    Attributes:
        path: the store directory.
        n_samples: N.  n_vertices: n_v.
    """

    def __init__(self, path: Path, root):
        self.path, self._root = path, root
        self._s = root["samples"]
        self.n_samples = int(root.attrs["n_samples"])
        self.n_vertices = int(self._s["displacements"].shape[1])

    def __repr__(self) -> str:
        counts = np.bincount(self.status.astype(np.int64), minlength=len(SampleStatus))
        return (f"Dataset({str(self.path)!r}, {self.n_samples} samples: {counts[SampleStatus.DONE]} done, "
                f"{counts[SampleStatus.FAILED]} failed, {counts[SampleStatus.PENDING]} pending; "
                f"{self.n_vertices} vertices)")

    def __len__(self) -> int:
        return self.n_samples

    def _array(self, name: str) -> np.ndarray:
        a = np.asarray(self._root[name][...])
        a.setflags(write=False)
        return a

    # -------------------------------------------------------------- per-sample arrays
    @cached_property
    def displacements(self) -> np.ndarray:
        """(N, n_v, 3) float32 vertex displacements, mm (NaN for samples not done)."""
        return self._array("samples/displacements")

    @cached_property
    def forces(self) -> np.ndarray:
        """(N, n_v, 3) float32 nodal forces, N (zero for pending samples)."""
        return self._array("samples/forces")

    def _per_sample(name: str, doc: str):  # noqa: N805 - helper evaluated in the class body
        def get(self):
            return self._array(f"samples/{name}")

        get.__doc__ = doc
        get.__name__ = name
        return cached_property(get)

    weights = _per_sample("weights", "(N, n_b, 3) float64 LBO weights W (NaN for pending samples).")
    alpha = _per_sample("alpha", "(N,) float64 force magnitude alpha, N (NaN for pending samples).")
    beta = _per_sample("beta", "(N,) float64 LBO share of test-2 fields; NaN for LBO samples.")
    seed = _per_sample("seed", "(N,) uint64 per-sample seeds (numpy default_rng(seed) draws the field).")
    status = _per_sample("status", "(N,) int8 :class:`~.codes.SampleStatus`: 0 pending, 1 done, 2 failed.")
    increments = _per_sample("increments", "(N,) int32 load increments (all attempts).")
    iterations = _per_sample("iterations", "(N,) int32 Newton iterations (all attempts).")
    factorizations = _per_sample("factorizations", "(N,) int32 matrix factorisations (all attempts).")
    attempts = _per_sample("attempts", "(N,) int8 solver attempts (1 + retries used).")
    load_fraction = _per_sample("load_fraction", "(N,) float64 share of the load reached (1 when done).")
    max_displacement = _per_sample("max_displacement", "(N,) float32 largest vertex displacement, mm (NaN unless done).")
    seconds = _per_sample("seconds", "(N,) float64 wall-clock solve time, s.")
    del _per_sample

    @cached_property
    def predicted(self) -> np.ndarray:
        """(N,) int8 :class:`~.codes.InitialGuess` of each solve: 0 zero (no reduced model yet),
        1 the reduced model's prediction, 2 the guess did not work (then zero), 3 a calibration
        pilot's solution of the previous round, 4 a basis sample's interim-model prediction, 5 a
        first-round pilot's own linear answer. All 0 in stores made before the predictor existed."""
        if "predicted" not in self._root["samples"]:
            return np.full(self.n_samples, InitialGuess.ZERO, dtype=np.int8)
        return self._array("samples/predicted")

    @cached_property
    def draws(self) -> dict[str, np.ndarray]:
        """Each sample's scenario draws, by name (:data:`~.schema.DRAWS`): ``gravity_direction``
        (N, 3) unit vectors, ``indent_centre`` (N,) int64 vertex ids (-1: none),
        ``indent_depth`` / ``indent_slide`` (N,) mm and ``indent_displacement`` (N, 3) mm (NaN:
        not drawn). Only the draws the scenario makes; empty for the paper's set-up."""
        samples = self._root["samples"]
        return {name: self._array(f"samples/{name}") for name in DRAWS if name in samples}

    @cached_property
    def parameters(self) -> dict[str, np.ndarray]:
        """Each sample's drawn uncertain parameters (N,) float64, by name without the ``param_``
        prefix (:data:`~.schema.PARAMETERS`): factors on E, density and the springs'
        stiffnesses, nu (NaN: nominal), the attached margin in mm; empty for a store whose
        scenario draws none."""
        samples = self._root["samples"]
        return {name[len("param_"):]: self._array(f"samples/{name}") for name in PARAMETERS if name in samples}

    @cached_property
    def instrument_poses(self) -> dict[str, dict[str, np.ndarray]]:
        """Each tracked instrument's per-sample pose, by instrument name
        (``samples/instrument_<name>_*``, :mod:`tissuecast.instruments`): ``tip`` and
        ``direction`` (N, 3) (mm, mesh frame; unit; NaN when away or pending), ``depth`` (N,) mm,
        ``contact`` (N,) int8 (1 touching, 0 away, -1 pending); empty without instruments."""
        samples = self._root["samples"]
        suffix = "_contact"
        names = sorted(k[len(INSTRUMENT_PREFIX):-len(suffix)] for k in samples.array_keys()
                       if k.startswith(INSTRUMENT_PREFIX) and k.endswith(suffix))
        return {name: {part: self._array(f"samples/{INSTRUMENT_PREFIX}{name}_{part}") for part in POSE_PARTS}
                for name in names}

    @cached_property
    def split_codes(self) -> np.ndarray:
        """(N,) int8 split codes (0 train, 1 valid, 2 test1, 3 test2)."""
        return self._array("samples/split")

    @cached_property
    def split(self) -> np.ndarray:
        """(N,) str split labels: 'train', 'valid', 'test1' or 'test2'."""
        names = np.array([SPLIT_NAMES[k] for k in sorted(SPLIT_NAMES)])
        return names[self.split_codes.astype(np.int64)]

    @property
    def failures(self) -> dict[int, str]:
        """Failure reason of every failed sample, by index."""
        return {int(k): v for k, v in (self._root.attrs.get("failures") or {}).items()}

    # -------------------------------------------------------------- set-up of the data set
    @cached_property
    def mesh(self):
        """The :class:`~tissuecast.mesh.TetMesh` the samples were computed on."""
        from ..mesh import TetMesh

        return TetMesh(self._array("mesh/points"), self._array("mesh/tets"))

    @cached_property
    def markers(self) -> np.ndarray:
        """(n_d,) int64 fiducial-marker vertex ids (0-based, pick order)."""
        return self._array("markers")

    @cached_property
    def scenario_arrays(self) -> dict[str, np.ndarray]:
        """The resolved scenario's stored arrays (:func:`~.schema.read_scenario_arrays`: pins,
        attached region, springs, materials, indentation access; for a store made before
        scenarios were recorded, its fixed vertices as the pins)."""
        return read_scenario_arrays(self._root)

    @property
    def reduced_arrays(self) -> dict[str, np.ndarray]:
        """The reduced-order predictor's ``basis`` (n_free, r), ``elements`` (k,) int64 and
        ``weights`` (k,) (``reduced/*``), once it is complete; empty before / without one."""
        if self._root.attrs.get("reduced") is None:
            return {}
        return {name: np.asarray(self._root[f"reduced/{name}"][...]) for name in ("basis", "elements", "weights")}

    def recipe(self, solver_factory: str | None = None) -> Recipe:
        """The :class:`~.worker.Recipe` the data set's samples are solved with: its config,
        mesh, LBO basis and scenario arrays, and its reduced-order predictor once built.

        Args:
            solver_factory: ``"module:function"`` replacing the FEM solver factory (for testing).
        """
        kw = {"solver_factory": solver_factory} if solver_factory else {}
        kw.update({f"reduced_{name}": a for name, a in self.reduced_arrays.items()})
        return Recipe(self.config_toml, np.asarray(self._root["mesh/points"][...]),
                      np.asarray(self._root["mesh/tets"][...]), self.basis, self.scenario_arrays, **kw)

    @cached_property
    def fixed(self) -> np.ndarray:
        """(k,) int64 fixed vertex ids (0-based)."""
        return self._array("fixed")

    @cached_property
    def basis(self):
        """The stored :class:`~tissuecast.forces.LBOBasis`."""
        return read_lbo_basis(self._root)

    @property
    def config_toml(self) -> str:
        """The configuration that made the data set, as TOML text."""
        return self._root.attrs["config_toml"]

    @cached_property
    def config(self) -> Config:
        """The configuration that made the data set."""
        return config_from_dict(tomllib.loads(self.config_toml))

    @property
    def attrs(self) -> dict:
        """All root attributes (schema, versions, calibration, ...)."""
        return dict(self._root.attrs)

    @property
    def scenario(self) -> dict:
        """The clinical scenario's summary (:meth:`tissuecast.scenario.Scenario.summary`:
        supports, springs, gravity, indentation, material draws); for a store made before
        scenarios were recorded, the paper's set-up (its pins and LBO forces)."""
        stored = self._root.attrs.get("scenario")
        if stored:
            return dict(stored)
        from ..scenario.describe import paper_summary

        return paper_summary(len(self.fixed))

    @property
    def calibration(self) -> dict | None:
        """The force-magnitude calibration record (None before calibration)."""
        return self._root.attrs.get("calibration")

    # -------------------------------------------------------------- selection / summary
    def select(self, split=None, status: str | None = "done") -> np.ndarray:
        """Indices (ascending int64) of the samples in ``split`` with ``status``.

        Args:
            split: a label ('train', 'valid', 'test1', 'test2'), a list of labels, or None (all).
            status: 'done' (default), 'failed', 'pending', or None (any).
        """
        keep = np.ones(self.n_samples, dtype=bool)
        if split is not None:
            labels = [split] if isinstance(split, str) else list(split)
            bad = [s for s in labels if s not in SPLIT_CODES]
            if bad:
                raise DatasetError(f"unknown split {bad[0]!r}; use one of {', '.join(SPLIT_CODES)}")
            keep &= np.isin(self.split_codes, [SPLIT_CODES[s] for s in labels])
        if status is not None:
            if status not in _STATUS_CODES:
                raise DatasetError(f"unknown status {status!r}; use one of {', '.join(_STATUS_CODES)}")
            keep &= self.status == _STATUS_CODES[status]
        return np.flatnonzero(keep)

    def _deformation_summary(self) -> dict:
        nr = self.nonrigid_part()
        done = self.status == SampleStatus.DONE
        share = nr / np.where(self.max_displacement > 0, self.max_displacement, np.nan)
        return {"nonrigid_part": max_displacement_stats(nr[done]),
                "nonrigid_part_by_split": {name: max_displacement_stats(nr[done & (self.split_codes == code)])
                                           for code, name in SPLIT_NAMES.items()},
                "nonrigid_share": max_displacement_stats(share[done])}

    def _predictor_summary(self) -> dict:
        done = self.status == SampleStatus.DONE
        out = {"model": self._root.attrs.get("reduced")}
        for code, name in _PREDICTOR_KEYS.items():
            sel = done & (self.predicted == code)
            out[name] = {"samples": int(sel.sum()),
                         "seconds_mean": float(self.seconds[sel].mean()) if sel.any() else 0.0,
                         "iterations_mean": float(self.iterations[sel].mean()) if sel.any() else 0.0,
                         "factorizations_mean": float(self.factorizations[sel].mean()) if sel.any() else 0.0}
        return out

    def nonrigid_part(self) -> np.ndarray:
        """(N,) float64 mm: each done sample's non-rigid part, the largest vertex residual after
        the best rigid fit of its whole displacement field (NaN unless done; see
        :func:`tissuecast.registration.nonrigid_part`)."""
        from ..registration import nonrigid_part

        out = np.full(self.n_samples, np.nan)
        done = np.flatnonzero(self.status == SampleStatus.DONE)
        points = self.mesh.points
        for s in range(0, done.size, 256):
            idx = done[s:s + 256]
            out[idx] = nonrigid_part(points, self._s["displacements"].get_orthogonal_selection(
                (idx, slice(None), slice(None))))
        return out

    def summary(self, *, deformation: bool = False) -> dict:
        """The scenario (:attr:`scenario`), counts by split and status, per-sample maximum displacement
        and timing statistics.

        Args:
            deformation: also the distribution of the non-rigid part of the done samples
                (reads every displacement field), overall, per split and as a share of the
                sample's peak displacement.
        """
        counts = {}
        for code, name in SPLIT_NAMES.items():
            in_split = self.split_codes == code
            counts[name] = {st: int(np.sum(in_split & (self.status == c))) for c, st in STATUS_NAMES.items()}
        done = self.status == SampleStatus.DONE
        by_split = {name: max_displacement_stats(self.max_displacement[done & (self.split_codes == code)])
                    for code, name in SPLIT_NAMES.items()}
        by_beta = {}
        test2 = done & (self.split_codes == SPLIT_CODES["test2"])
        for b in np.unique(self.beta[test2]):
            by_beta[f"{b:g}"] = max_displacement_stats(self.max_displacement[test2 & (self.beta == b)])
        sec = self.seconds[self.status != SampleStatus.PENDING]
        its = self.iterations[done]
        incs = self.increments[done]
        return {
            "path": str(self.path), "n_samples": self.n_samples, "n_vertices": self.n_vertices,
            "scenario": self.scenario,
            "counts": counts,
            "totals": {st: int(np.sum(self.status == c)) for c, st in STATUS_NAMES.items()},
            "max_displacement": max_displacement_stats(self.max_displacement[done]),
            "max_displacement_by_split": by_split,
            "max_displacement_by_beta": by_beta,
            "timing": {"solved": int(len(sec)), "seconds_total": float(sec.sum()) if len(sec) else 0.0,
                       "seconds_mean": float(sec.mean()) if len(sec) else 0.0,
                       "seconds_max": float(sec.max()) if len(sec) else 0.0,
                       "increments_mean": float(incs.mean()) if len(incs) else 0.0,
                       "iterations_mean": float(its.mean()) if len(its) else 0.0,
                       "retried": int(np.sum(self.attempts[self.status != SampleStatus.PENDING] > 1))},
            **(self._deformation_summary() if deformation else {}),
            "predictor": self._predictor_summary(),
            "calibration": self.calibration,
            "failures": self.failures,
        }
