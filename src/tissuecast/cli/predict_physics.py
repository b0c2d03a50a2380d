"""``tissuecast predict MODEL --markers FILE --physics STORE``: the field through the physics.

Instead of the learned model, the physics inverse (:class:`tissuecast.inverse.MarkerInverse`)
solves, frame by frame, for the loads and the parameters the operating room does not know whose
finite-element solution (the data set's own simulator: its mesh, elements, supports and load
family) puts the model's markers where they were tracked. It takes seconds (parameters known)
to minutes (parameters drawn) a frame, not the model's microseconds: for a frame that can wait
(before a resection, to check the model). The model gives the markers and its input gate; the
data set gives the simulator and the force magnitude.

The loads navigation knows come in as for the model: each tracked instrument's pose
(``--instrument``, required when the scenario pushes with one; where it pushes is a load the
simulator needs) and the direction of gravity in surgery (``--gravity``, model frame; default
the scenario's planned ``scenario.gravity.surgery_direction``). An untracked marker is left out
of the fit. The estimate is the maximum a posteriori one with the scenario's parameter ranges as
priors; E and the surroundings' stiffness come back only up to a common scale (a stiffer body
under larger loads looks the same to the markers). Where the attached margin is searched, the
field written is the posterior mean over the held sets finished (``--physics-estimate mean``,
the default) or the likeliest held set's (``likeliest``). A frame is given ``--time-limit`` seconds
(:data:`TIME_LIMIT` by default, 0 for none): past it the search stops and the best estimate
reached is written, said so (the first held set is iterated to convergence regardless); without
a limit the answer does not depend on the machine's speed or load (the solves inside are capped
by counts of iterations and factorisations). A fit
whose worst marker misses by more than
:data:`~tissuecast.inverse.MISFIT_NOISES` noise standard deviations is flagged with a warning
(a frame the simulator's family does not explain, or a search that missed; measured in
docs/uncertainty.md). Each vertex gets the
estimate's posterior spread (:attr:`~tissuecast.inverse.InverseResult.spread`, mm), written
where the learned model writes its ensemble's (``uncertainty_mm`` point data and CSV column):
what the markers' noise and the held sets leave open within the simulator's family; no alarm.
A JSON output (``--out F.json``) also gets each sample's estimate under ``physics``
(:func:`record`: the parameters, the markers' fit, the held sets).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ModelError

if TYPE_CHECKING:
    from ..inverse import MarkerInverse

__all__ = ["physics_fields", "check_physics_options", "describe", "record", "misfit_warning", "TIME_LIMIT"]

#: Default wall-clock seconds of one frame (what frames of the shipped presets take:
#: docs/uncertainty.md).
TIME_LIMIT = 600.0


def check_physics_options(args) -> None:
    """Refuse the options that belong to the learned model (one error naming the fix)."""
    clash = [flag for flag, on in (("--uncertainty", args.uncertainty), ("--coverage", args.coverage is not None),
                                   ("--false-alarm", args.false_alarm is not None), ("--parameter", bool(args.parameter)),
                                   (f"--method {args.method}", args.method != "mlp")) if on]
    if clash:
        raise ModelError(f"--physics solves with the data set's simulator; {', '.join(clash)} belong to the learned "
                         "model: drop them, or drop --physics")
    if args.noise is not None and not (np.isfinite(args.noise) and args.noise > 0):
        raise ModelError(f"--noise must be a positive number of mm, got {args.noise!r}")
    if args.attached_margin_sd is not None and args.attached_margin is None:
        raise ModelError("--attached-margin-sd is the measured margin's uncertainty: give the margin with --attached-margin")
    if args.physics_estimate is not None and args.attached_margin is not None and args.attached_margin_sd is None:
        raise ModelError("--physics-estimate chooses among the held sets searched; with --attached-margin alone one held "
                         "set is solved: drop one of the two (or give --attached-margin-sd)")
    if not (np.isfinite(args.time_limit) and args.time_limit >= 0):
        raise ModelError(f"--time-limit must be a number of seconds >= 0 (0: none), got {args.time_limit!r}")


def _dataset_for(model, path: str):
    """The data set at ``path``, checked to be of the model's mesh."""
    from ..dataset import open_dataset

    if not Path(path).exists():
        raise FileNotFoundError(f"--physics {path!r}: no data set there; give the store the model was trained on")
    ds = open_dataset(path)
    if ds.mesh.fingerprint() != model.mesh.fingerprint():
        raise ModelError(f"--physics {path!r} was simulated on another mesh than the model's; give the store the model "
                         "was trained on")
    return ds


def physics_fields(args, model, d: np.ndarray, missing: np.ndarray) -> tuple[np.ndarray, list, "MarkerInverse"]:
    """The physics inverse's fields of every sample.

    Args:
        args: the ``predict`` arguments (``physics``, ``instrument``, ``gravity``, ``noise``,
            ``time_limit``, ``attached_margin``, ``attached_margin_sd``, ``physics_estimate``).
        model: the :class:`~tissuecast.surrogate.DeformationModel` (markers, input gate).
        d: (B, n_d, 3) marker displacements, mm (NaN where ``missing``).
        missing: (B, n_d) bool, the untracked markers.

    Returns:
        ``(fields (B, n, 3) mm, [InverseResult] one per sample, the MarkerInverse that solved
        them: its estimated parameters and its marker noise)``.

    Raises:
        InputRejected: the model's input gate refuses a sample's markers.
        ModelError / ConfigError: a data set of another mesh, a missing instrument pose, a pose
            or gravity direction the simulator cannot take.
    """
    from ..inverse import NOISE_MM, MarkerInverse

    B = d.shape[0]
    if model.input_gate is not None:
        model.input_gate.enforce(d.reshape(B, -1), missing)
    ds = _dataset_for(model, args.physics)
    inv = MarkerInverse.from_dataset(ds, model.markers, noise=args.noise or NOISE_MM)
    note = underdetermined_note(inv, 3 * len(model.markers))
    if note:
        print(note, flush=True)
    names = [inst.name for inst in inv.scenario.config.instruments]
    poses = {}
    if names and not args.instrument:
        raise ModelError(f"the simulator pushes with {names}: give their poses with --instrument FILE "
                         '(e.g. {"retractor": {"contact": false}} when it is away)')
    if args.instrument:
        from ..instruments import ReferenceSurface
        from .predict_inputs import read_instrument_file

        poses = read_instrument_file(Path(args.instrument), names, ReferenceSurface.of(model.mesh), B)
    from ..fem.linear import one_blas_thread

    fields, results = [], []
    for b in range(B):
        draw = inv.scenario.frame_draw({n: poses[n][b] for n in names}, args.gravity)
        print(f"sample {b}: solving through the physics (seconds to minutes a frame) ...", flush=True)
        with one_blas_thread():  # as the data set's workers solve: faster, the same bits
            res = inv.solve(np.where(missing[b][:, None], np.nan, d[b]), draw, time_limit=args.time_limit or None,
                            attached_margin=args.attached_margin, attached_margin_sd=args.attached_margin_sd,
                            estimate=args.physics_estimate,
                            progress=lambda text, b=b: print(f"sample {b}: {text}", flush=True))
        fields.append(res.field)
        results.append(res)
    return np.stack(fields), results, inv


def underdetermined_note(inverse, coordinates: int) -> str | None:
    """A note where ``inverse`` estimates more unknowns (:attr:`~tissuecast.inverse.MarkerInverse.n_unknowns`)
    than the ``coordinates`` tracked marker coordinates determine, else None."""
    n = inverse.n_unknowns
    if n <= coordinates:
        return None
    return (f"note: the physics inverse estimates {n} unknowns from {coordinates} marker coordinates: the prior decides "
            "what the markers do not see, and the learned model (the mean over the simulations) is then about as accurate "
            "and far faster (on the paper preset: docs/uncertainty.md)")


def misfit_warning(res, inverse) -> str | None:
    """The warning of a fit that ``inverse`` flags (:meth:`~tissuecast.inverse.MarkerInverse.flags`:
    its worst marker misses by more than :data:`~tissuecast.inverse.MISFIT_NOISES` noise standard
    deviations), else None."""
    if not inverse.flags(res):
        return None
    noise = inverse.noise
    return (f"WARNING: a marker is {res.marker_misfit:.3f} mm from where the solution puts it ({res.marker_misfit / noise:.0f} "
            f"x the tracking noise of {noise:g} mm): no load and parameters of the simulator explain this frame (or "
            "the search missed them); do not take this field over the learned model's, whose error bounds and alarm "
            "judge the frame")


def record(res, inverse) -> dict:
    """What ``inverse`` estimated for one frame (``res``), for ``predict``'s JSON output: the
    estimated parameters (factors on the nominal ones; Poisson's ratio; the attached margin in
    mm where it is drawn), the markers' fit, the held sets and the field's estimate, whether the
    fit is flagged or the search cut short, solves and seconds."""
    p = res.parameters
    names = list(inverse.estimated) + (["attached_margin"] if inverse.margins.size else [])
    return {"parameters": {name: float(getattr(p, name)) for name in names},
            "marker_misfit_mm": float(res.marker_misfit), "flagged": bool(inverse.flags(res)),
            "held_sets": int(res.held_sets), "estimate": res.estimate, "likeliest_weight": float(res.likeliest_weight),
            "complete": bool(res.complete), "solves": int(res.solves), "seconds": float(res.seconds)}


def describe(res, estimated=()) -> str:
    """One line of an inverse's estimate: misfit, the ``estimated`` parameters' values (factors
    on the nominal ones; Poisson's ratio), the held sets, the posterior spread, solves and time."""
    p = res.parameters
    parts = [f"markers fitted to {res.marker_misfit:.3f} mm"]
    for name in estimated:
        parts.append(f"{name} {getattr(p, name):.3g}")
    if res.held_sets > 1:
        share = f"{100 * res.likeliest_weight:.0f} % of the posterior"
        how = (f"{res.held_sets} held sets averaged, the likeliest {share}" if res.estimate == "mean"
               else f"the likeliest of {res.held_sets} held sets, {share}")
        parts.append(f"attached margin {p.attached_margin:+.2f} mm ({how})")
    parts.append(f"posterior spread median {np.nanmedian(res.spread):.3f} / max {np.nanmax(res.spread):.3f} mm")
    cut = "" if res.complete else "; cut short by --time-limit: the best estimate reached by then"
    return ", ".join(parts) + f"; {res.solves} solves, {res.seconds:.1f} s{cut}"
