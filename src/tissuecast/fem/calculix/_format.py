"""Number and id formatting shared by the deck's writers (:mod:`._deck`, :mod:`._scenario`)."""

from __future__ import annotations

import numpy as np

__all__ = ["number_text", "id_lines"]


def number_text(x) -> str:
    """Text of a float that ccx reads: the shortest exact form, or 14 digits if that is longer
    than 20 characters (ccx rejects longer numbers such as ``-2.786959021906976E-05``)."""
    text = repr(float(x))
    digits = 13
    while len(text) > 20:
        text = f"{float(x):.{digits}e}"
        digits -= 1
    return text


def id_lines(ids: np.ndarray, per_line: int = 8) -> list[str]:
    return [", ".join(str(int(i)) for i in ids[k : k + per_line]) for k in range(0, len(ids), per_line)]
