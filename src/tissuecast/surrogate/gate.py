"""The input gate: marker input that no simulation could have produced is refused, always.

Unlike the trust layer's alarm (:mod:`.trust`, calibrated, statistical), the gate needs no
calibration and is part of every model: it knows, from the simulated samples the model was
fitted on, each marker's largest displacement and the range of each marker pair's distance
(as a share of the reference distance: the strain the simulations put between the two
markers). An input is refused, naming the marker (its index in the input, 0-based, and its
vertex id), when

- a tracked marker's displacement is not a finite number (NaN, inf);
- a marker is displaced more than :data:`DISPLACEMENT_FACTOR` times the largest displacement
  of that marker in any simulated sample (plus :data:`TOLERANCE_MM` for tracking noise): a
  tracking glitch, a unit error, a marker torn off;
- the distance between two markers leaves the simulated range widened on each side by that
  range's own width plus :data:`STRAIN_MARGIN` of the reference distance (plus
  :data:`TOLERANCE_MM`): a body cannot stretch or shrink so, so markers are swapped,
  mislabelled or mistracked. The marker named is the one in the most such pairs.

Everything inside passes unchanged (predictions of valid input are those of the model without
a gate). The gate's ranges are stored in ``model.json`` (``input_gate``); a folder written
before the gate derives them: from the trust layer's stored training inputs where it has one,
else from the PCA basis (:meth:`InputGate.from_pca`). Lengths in mm.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..errors import InputRejected

__all__ = ["InputGate", "GateVerdict", "DISPLACEMENT_FACTOR", "STRAIN_MARGIN", "TOLERANCE_MM", "PCA_DRAWS"]

#: A marker displaced more than this many times its largest simulated displacement is refused.
DISPLACEMENT_FACTOR = 3.0
#: Strain (share of the reference distance) allowed beyond the simulated range of a marker pair,
#: on top of the range's own width.
STRAIN_MARGIN = 0.1
#: Tracking noise allowed on every limit, mm.
TOLERANCE_MM = 2.0
#: Gaussian draws from the PCA basis that stand in for the training inputs of old model folders.
PCA_DRAWS = 4096


@dataclass(frozen=True)
class GateVerdict:
    """The gate's verdict on one input.

    Attributes:
        refused: the input is refused.
        reason: ``""``, ``"non-finite"``, ``"displacement"`` or ``"stretch"``.
        marker: index of the marker named (0-based, in the input's marker order), -1 if none.
        vertex: its vertex id (0-based), -1 if none.
        message: one line saying what is wrong and what to check (empty when passed).
    """

    refused: bool = False
    reason: str = ""
    marker: int = -1
    vertex: int = -1
    message: str = ""


@dataclass(frozen=True, eq=False)
class InputGate:
    """Limits of plausible marker input.

    Attributes:
        markers: (n_d,) int64 0-based vertex ids, in input order.
        reference: (n_d, 3) reference (undeformed) marker positions, mm.
        max_displacement: (n_d,) largest displacement of each marker over the simulated samples, mm.
        stretch: (P, 2) least and largest distance of each marker pair over the simulated
            samples as a share of the reference distance (pairs in ``itertools.combinations`` order).
        source: where the ranges come from: ``"training"`` (the fitted samples),
            ``"trust-file"`` (an old folder's trust layer inputs) or ``"pca"`` (an estimate).
    """

    markers: np.ndarray
    reference: np.ndarray
    max_displacement: np.ndarray
    stretch: np.ndarray
    source: str = "training"

    def __post_init__(self):
        pairs = np.array(list(itertools.combinations(range(len(self.markers)), 2)), dtype=np.int64).reshape(-1, 2)
        length = np.linalg.norm(self.reference[pairs[:, 0]] - self.reference[pairs[:, 1]], axis=1)
        s = np.asarray(self.stretch, dtype=np.float64).reshape(-1, 2)
        widen = (s[:, 1] - s[:, 0]) + STRAIN_MARGIN
        object.__setattr__(self, "_pairs", pairs)
        object.__setattr__(self, "_distance_limits",
                           np.stack([np.maximum(length * (s[:, 0] - widen) - TOLERANCE_MM, 0.0),
                                     length * (s[:, 1] + widen) + TOLERANCE_MM], axis=1))
        object.__setattr__(self, "_displacement_limits",
                           DISPLACEMENT_FACTOR * np.asarray(self.max_displacement, dtype=np.float64) + TOLERANCE_MM)
        object.__setattr__(self, "_passed", None)  # the _key of the last input inspect() or enforce() let through

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_inputs(cls, markers, reference, X, source: str = "training") -> "InputGate":
        """The gate of simulated marker displacements X (N, n_d, 3) or (N, 3 n_d) mm."""
        ref = np.asarray(reference, dtype=np.float64)
        d = np.asarray(X, dtype=np.float64).reshape(-1, len(ref), 3)
        pairs = list(itertools.combinations(range(len(ref)), 2))
        x = ref + d
        stretch = np.zeros((len(pairs), 2))
        for p, (a, b) in enumerate(pairs):
            r = np.linalg.norm(x[:, a] - x[:, b], axis=1) / max(np.linalg.norm(ref[a] - ref[b]), 1e-12)
            stretch[p] = r.min(), r.max()
        return cls(np.asarray(markers, dtype=np.int64), ref, np.linalg.norm(d, axis=2).max(axis=0), stretch, source)

    @classmethod
    def from_pca(cls, markers, reference, basis, seed: int = 0) -> "InputGate":
        """An estimate for a model folder written before the gate, without a trust layer:
        :data:`PCA_DRAWS` seeded draws of the PCA weights from independent normal laws of the
        components' variances (the training fields' Gaussian model) stand in for the inputs."""
        mk = np.asarray(markers, dtype=np.int64)
        cols = (3 * mk[:, None] + np.arange(3)).ravel()
        w = np.random.default_rng(seed).standard_normal((PCA_DRAWS, basis.n_components)) * np.sqrt(basis.explained_variance)
        X = basis.mean[cols] + w @ basis.components[:, cols]
        return cls.from_inputs(mk, reference, X, source="pca")

    # ------------------------------------------------------------------ verdicts
    def inspect(self, d, missing=None) -> list[GateVerdict]:
        """One verdict per input of ``d`` (B, 3 n_d) mm; ``missing`` (B, n_d) bool marks untracked markers (not checked).

        An input every verdict lets through is remembered as :meth:`enforce` remembers it."""
        return self._inspect(d, missing, self._key(d, missing))

    def _inspect(self, d, missing, key: tuple) -> list[GateVerdict]:
        d = np.asarray(d, dtype=np.float64).reshape(len(d), -1, 3)
        if (missing is None or not np.any(missing)) and self._all_pass(d):  # the usual input, in a few products
            object.__setattr__(self, "_passed", key)
            return [GateVerdict()] * len(d)
        tracked = np.ones(d.shape[:2], dtype=bool) if missing is None else ~np.asarray(missing, dtype=bool)
        finite = np.isfinite(d).all(axis=2) | ~tracked
        with np.errstate(invalid="ignore", over="ignore"):
            over = np.where(tracked & finite, np.linalg.norm(d, axis=2) / self._displacement_limits, 0.0)
            x = self.reference + np.where(finite[..., None], d, 0.0)
            a, b = self._pairs[:, 0], self._pairs[:, 1]
            dist = np.linalg.norm(x[:, a] - x[:, b], axis=2)
        lo, hi = self._distance_limits[:, 0], self._distance_limits[:, 1]
        bad_pair = ((dist < lo) | (dist > hi)) & tracked[:, a] & tracked[:, b] & finite[:, a] & finite[:, b]
        verdicts = []
        for s in range(len(d)):
            if not finite[s].all():
                verdicts.append(self._verdict("non-finite", int(np.flatnonzero(~finite[s])[0]), d[s]))
            elif over[s].max(initial=0.0) > 1.0:
                verdicts.append(self._verdict("displacement", int(over[s].argmax()), d[s]))
            elif bad_pair[s].any():
                verdicts.append(self._stretch_verdict(bad_pair[s], dist[s]))
            else:
                verdicts.append(GateVerdict())
        if not any(v.refused for v in verdicts):
            object.__setattr__(self, "_passed", key)
        return verdicts

    def _all_pass(self, d: np.ndarray) -> bool:
        """Whether every input of ``d`` (B, n_d, 3) mm, every marker tracked, passes (finite,
        within the displacement limits and every pair's distance limits)."""
        if not np.isfinite(d).all():
            return False
        if (np.einsum("bjk,bjk->bj", d, d) > self._displacement_limits**2).any():
            return False
        x = self.reference + d
        gap = x[:, self._pairs[:, 0]] - x[:, self._pairs[:, 1]]
        dist = np.sqrt(np.einsum("bpk,bpk->bp", gap, gap))
        return bool(((dist >= self._distance_limits[:, 0]) & (dist <= self._distance_limits[:, 1])).all())

    @staticmethod
    def _key(d, missing) -> tuple:
        """What identifies an input (B, 3 n_d) mm and its ``missing`` mask (no marker missing:
        None; an untracked marker's coordinates, NaN from a tracker or filled in by a model, do
        not count)."""
        values = np.array(d, dtype=np.float64).reshape(len(d), -1)
        if missing is not None:
            missing = np.ascontiguousarray(missing, dtype=bool)
            if missing.any():
                values.reshape(len(values), -1, 3)[missing.reshape(len(values), -1)] = 0.0
            else:
                missing = None
        return values.shape, values.tobytes(), None if missing is None else missing.tobytes()

    def enforce(self, d, missing=None) -> None:
        """Raise :class:`~tissuecast.errors.InputRejected` for the first refused input of ``d`` (B, 3 n_d) mm.

        The input it last let through (here or in :meth:`inspect`) is remembered (its bytes): the
        parts of a composed model share one gate, and each checks the input again on its way
        down, after a server has inspected it; the same values pass at once."""
        key = self._key(d, missing)
        if key == self._passed:
            return
        for s, v in enumerate(self._inspect(d, missing, key)):
            if v.refused:
                where = f"sample {s}: " if len(d) > 1 else ""
                raise InputRejected(f"{where}{v.message}", reason=v.reason, marker=v.marker, vertex=v.vertex,
                                    sample=s)

    def _name(self, j: int) -> str:
        return f"marker {j} (input index {j}, vertex {int(self.markers[j])})"

    def _verdict(self, reason: str, j: int, dj: np.ndarray) -> GateVerdict:
        if reason == "non-finite":
            text = (f"marker input refused: {self._name(j)} has a non-finite displacement (NaN or inf) "
                    f"{dj[j].tolist()}: the tracker lost it: mark it untracked or re-acquire it")
        else:
            text = (f"marker input refused: {self._name(j)} is displaced {np.linalg.norm(dj[j]):.4g} mm, more than "
                    f"{DISPLACEMENT_FACTOR:g} x the largest simulated displacement of that marker "
                    f"({self.max_displacement[j]:.3g} mm): "
                    f"{self._mix_up(dj) or 'a tracking glitch, a unit error or a slipped marker?'}")
        return GateVerdict(True, reason, j, int(self.markers[j]), text)

    def _mix_up(self, dj: np.ndarray) -> str:
        """The fix where an input refused for its displacements (n_d, 3) mm reads as plausible
        once taken the other way (positions given as displacements, or the reverse); else ""."""
        for other, fix in ((dj - self.reference, "these look like marker positions, not displacements: use "
                            "predict_from_positions (CLI: --positions, or a file with \"positions\")"),
                           (dj + self.reference, "these look like marker displacements given as positions: use predict "
                            "(CLI: without --positions)")):
            if (np.linalg.norm(other, axis=1) <= self._displacement_limits).all():
                return fix
        return ""

    def _stretch_verdict(self, bad: np.ndarray, dist: np.ndarray) -> GateVerdict:
        counts = np.bincount(self._pairs[bad].ravel(), minlength=len(self.markers))
        j = int(counts.argmax())
        lengths = np.linalg.norm(self.reference[self._pairs[:, 0]] - self.reference[self._pairs[:, 1]], axis=1)
        mine = np.flatnonzero(bad & ((self._pairs[:, 0] == j) | (self._pairs[:, 1] == j)))
        p = int(mine[np.argmax(np.abs(np.log(np.maximum(dist[mine], 1e-12) / lengths[mine])))])  # its worst pair
        k = int(self._pairs[p, 1] if self._pairs[p, 0] == j else self._pairs[p, 0])
        length = np.linalg.norm(self.reference[j] - self.reference[k])
        lo, hi = self.stretch[p]
        text = (f"marker input refused: {self._name(j)} is {dist[p]:.1f} mm from marker {k} (vertex "
                f"{int(self.markers[k])}), {dist[p] / length:.2f} x their reference distance {length:.1f} mm; the "
                f"simulations stretch it {lo:.3f}-{hi:.3f} x ({int(counts[j])} of its pairs out of range): swapped, "
                "mislabelled or mistracked markers?")
        return GateVerdict(True, "stretch", j, int(self.markers[j]), text)

    # ------------------------------------------------------------------ storage
    def as_dict(self) -> dict:
        """JSON-able form (``model.json``'s ``input_gate``)."""
        return {"source": self.source, "max_displacement_mm": self.max_displacement.tolist(),
                "stretch": self.stretch.tolist(), "displacement_factor": DISPLACEMENT_FACTOR,
                "strain_margin": STRAIN_MARGIN, "tolerance_mm": TOLERANCE_MM}

    @classmethod
    def from_dict(cls, markers, reference, doc: dict) -> "InputGate":
        return cls(np.asarray(markers, dtype=np.int64), np.asarray(reference, dtype=np.float64),
                   np.asarray(doc["max_displacement_mm"], dtype=np.float64),
                   np.asarray(doc["stretch"], dtype=np.float64).reshape(-1, 2), str(doc.get("source", "training")))
