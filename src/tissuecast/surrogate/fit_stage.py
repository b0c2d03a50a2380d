"""What a network fit is part of, for its log lines: the model, its markers-only fallback, a
calibration fold model, an ensemble member, the nominal expert.

A fit deep inside :meth:`~.model.DeformationModel.fit` cannot tell which of a run's many
networks it trains; its callers say so with :func:`fit_stage`, nested as they are called
(``"nominal expert, markers-only fallback, calibration fold 2/5"``), and :mod:`.mlp` writes
:func:`stage_text` into its lines. A context variable, so threads and nested calls keep their own.
"""

from __future__ import annotations

import contextlib
import contextvars

__all__ = ["fit_stage", "stage_text"]

_STAGES: contextvars.ContextVar[tuple[str, ...]] = contextvars.ContextVar("tissuecast_fit_stages", default=())


@contextlib.contextmanager
def fit_stage(label: str):
    """Within the block, network fits are labelled ``label`` (after the enclosing blocks' labels)."""
    token = _STAGES.set(_STAGES.get() + (str(label),))
    try:
        yield
    finally:
        _STAGES.reset(token)


def stage_text() -> str:
    """The enclosing labels as ``" (a, b)"``; ``""`` outside every :func:`fit_stage` block."""
    stages = _STAGES.get()
    return f" ({', '.join(stages)})" if stages else ""
