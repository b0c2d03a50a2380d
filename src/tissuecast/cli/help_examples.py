"""The "examples:" section at the end of a command's ``--help``.

``with_examples(("tissuecast predict MODEL --markers m.csv", "what it does"), ...)`` gives the
keyword arguments of ``add_parser`` (``epilog`` and a formatter that keeps the examples' lines
as written while it wraps the description as usual). Every example is parsed by the tests.
"""

from __future__ import annotations

import argparse

__all__ = ["ExamplesFormatter", "with_examples", "EXAMPLES_HEADING"]

EXAMPLES_HEADING = "examples:"


class ExamplesFormatter(argparse.HelpFormatter):
    """argparse's formatter, except that an epilog opening with :data:`EXAMPLES_HEADING` keeps its lines."""

    def _fill_text(self, text, width, indent):
        if text.startswith(EXAMPLES_HEADING):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def with_examples(*examples: tuple[str, str]) -> dict:
    """``add_parser`` keywords for a help ending in ``examples`` ((command line, what it does), ...)."""
    lines = [EXAMPLES_HEADING]
    for command, what in examples:
        lines += [f"  {command}", f"      {what}"]
    return {"epilog": "\n".join(lines), "formatter_class": ExamplesFormatter}
