"""Entry point of the ``tissuecast`` command.

Each subcommand lives in its own module of this package, exposing
``register(subparsers)`` which adds its parser and sets ``func=run`` where
``run(args) -> int`` does the work. Errors derived from
:class:`~tissuecast.errors.TissuecastError` (and missing files) are printed as one line,
``error: ...``, with exit status 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import signal
import sys
import threading

from .. import __version__
from ..errors import TissuecastError

#: Exit status of a run stopped by a clear error (argparse uses the same for bad arguments),
#: and of one interrupted by Ctrl+C (128 + SIGINT, the shells' convention).
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130
#: Exit status of a run stopped by SIGTERM (``kill``, ``timeout``, a scheduler): 128 + SIGTERM.
EXIT_TERMINATED = 143

# subcommand name -> module in tissuecast.cli (imported lazily so `tissuecast --help` is fast)
COMMANDS: dict[str, str] = {  # in the order a user meets them: get started, the pipeline, use a model, set up, study
    "demo": "demo_cmd",
    "run": "run_cmd",
    "simulate": "simulate_cmd",
    "train": "train_cmd",
    "evaluate": "evaluate_cmd",
    "predict": "predict_cmd",
    "serve": "serve_cmd",
    "config": "config_cmd",
    "scenario": "scenario_cmd",
    "mesh": "mesh_cmd",
    "markers": "markers_cmd",
    "dataset": "dataset_cmd",
    "export-inp": "export_inp_cmd",
    "study": "study_cmd",
    "experts": "experts_cmd",
}
#: Two-word commands (command, action) -> module; e.g. `tissuecast markers plan STORE`.
ACTIONS: dict[tuple[str, str], str] = {("markers", "plan"): "markers_plan_cmd"}


def build_parser(only: str | None = None, action_module: str | None = None) -> argparse.ArgumentParser:
    """The parser; with ``only``, just that command's module is imported (``action_module``
    instead of it for a two-word command of :data:`ACTIONS`)."""
    parser = argparse.ArgumentParser(
        prog="tissuecast",
        description="Real-time soft-tissue deformation from fiducial markers (units: mm, N, MPa; vertex ids 0-based).",
        epilog="Start with `tissuecast demo` (the whole pipeline on the built-in phantom, a few minutes), then "
               "`tissuecast run CONFIG` or a packaged preset (quick, paper, embedded); `tissuecast COMMAND --help` "
               "says what a command reads and writes, with examples.",
    )
    parser.add_argument("--version", action="version", version=f"tissuecast {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=f"(run `tissuecast {name} --help`)", add_help=False)
            continue
        importlib.import_module(f"{__package__}.{action_module or module}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 user error, 1 unexpected failure)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    # import only the chosen subcommand's module when it is clear which one it is
    words = [a for a in argv if not a.startswith("-")][:2]
    first = words[0] if words else None
    if first is not None and first not in COMMANDS:  # argparse would list every choice without a suggestion
        close = difflib.get_close_matches(first, COMMANDS, n=1)
        hint = f"; did you mean `tissuecast {close[0]}`?" if close else f"; the commands: {', '.join(COMMANDS)}"
        print(f"tissuecast: error: unknown command {first!r}{hint}", file=sys.stderr)
        return EXIT_ERROR
    parser = build_parser(first if first in COMMANDS else None, ACTIONS.get(tuple(words)))
    args = parser.parse_args(argv)
    _configure_logging(logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else EXIT_ERROR
    _stop_on_sigterm()
    try:
        return int(args.func(args) or 0)
    except (TissuecastError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        print("terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted", file=sys.stderr)
        return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
    except BrokenPipeError:  # e.g. `tissuecast markers ... | head`
        sys.stderr.close()
        return 0


class Terminated(KeyboardInterrupt):
    """SIGTERM received: raised in the main thread so that the run stops as after Ctrl+C
    (worker processes stopped, finished samples saved, no leaked semaphores)."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def _stop_on_sigterm() -> None:
    """Turn SIGTERM into :class:`Terminated` (a KeyboardInterrupt) in the main thread, so a
    ``kill`` or ``timeout`` unwinds the run like Ctrl+C instead of ending the process at once."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at emit time (so redirection and capture work)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


def _configure_logging(level: int) -> None:
    """Route the ``tissuecast`` loggers to stderr at ``level``; the root logger is left alone."""
    logger = logging.getLogger("tissuecast")
    for h in [h for h in logger.handlers if isinstance(h, _StderrHandler)]:
        logger.removeHandler(h)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
