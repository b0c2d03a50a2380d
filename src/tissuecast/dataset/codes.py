"""The integer codes a data-set store holds: each sample's status and the start of its solve.

Written by :class:`~.store.StoreWriter` into ``samples/status`` and ``samples/predicted``
(int8) and read back by :class:`~.reader.Dataset`; the values are part of the store schema
(``docs/dataset-schema.md``) and never change.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = ["SampleStatus", "InitialGuess", "STATUS_NAMES"]


class SampleStatus(IntEnum):
    """``samples/status``: where a sample stands."""

    PENDING = 0  # not solved yet (solved on the next run)
    DONE = 1  # converged: its displacements are stored
    FAILED = 2  # no convergence after every retry: the reason is in the ``failures`` attribute

    @property
    def label(self) -> str:
        """The name used in ``status_labels``, summaries and ``Dataset.select``."""
        return self.name.lower()


class InitialGuess(IntEnum):
    """``samples/predicted``: what the full solve that made a sample started from."""

    ZERO = 0  # zero displacement (no reduced model yet, or none configured)
    REDUCED_MODEL = 1  # the reduced-order model's prediction
    GUESS_FAILED = 2  # the guess did not work (no prediction, or no convergence from it): then zero
    PREVIOUS_ROUND = 3  # a calibration pilot's own solution of the previous calibration round
    INTERIM_MODEL = 4  # a reduced-model basis sample: the prediction of a model of the pilots' solutions
    LINEAR_ANSWER = 5  # a first-round calibration pilot: its LBO field's linear answer at the round's alpha


#: ``{code: label}`` of the sample status, as stored in the ``status_labels`` attribute.
STATUS_NAMES: dict[int, str] = {int(s): s.label for s in SampleStatus}
