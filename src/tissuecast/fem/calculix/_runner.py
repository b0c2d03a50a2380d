"""Run the ``ccx`` program on an input deck and detect failures."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from ...errors import ConvergenceError, DependencyError, SolverSetupError
from ._results import StaSummary, read_sta, residual_history

__all__ = ["CcxRun", "ccx_executable", "run_ccx"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CcxRun:
    """A finished ``ccx`` run: result files, progress, wall time (s) and the largest residual
    force component (N) after every iteration."""

    inp: Path
    dat: Path
    frd: Path
    sta: Path
    log: Path
    seconds: float
    summary: StaSummary
    residual_history: tuple[float, ...] = ()


def ccx_executable(executable: str | None = None) -> str:
    """Path of the ``ccx`` program (``executable`` or ``$TISSUECAST_CCX`` or ``ccx`` on PATH)."""
    name = executable or os.environ.get("TISSUECAST_CCX") or "ccx"
    found = shutil.which(name)
    if not found:
        raise DependencyError(
            f"the CalculiX solver {name!r} was not found on PATH; install it "
            "(Debian/Ubuntu: apt-get install calculix-ccx) or set TISSUECAST_CCX to its path"
        )
    return found


def run_ccx(inp_path, *, threads: int = 1, timeout: float | None = None, executable: str | None = None) -> CcxRun:
    """Run ``ccx`` on an input deck, in the deck's folder.

    Args:
        inp_path: the ``.inp`` file; results go next to it (``.dat``, ``.frd``, ``.sta``,
            ``.cvg`` and ``.log`` holding ccx's standard output).
        threads: CPU threads for ccx (OMP_NUM_THREADS, CCX_NPROC_*).
        timeout: seconds before ccx is killed; None = no limit.
        executable: ccx program to use (default: see :func:`ccx_executable`).

    Returns:
        A :class:`CcxRun`.

    Raises:
        DependencyError: ccx is not installed.
        ConvergenceError: ccx stopped with an error, before the full load (increment below
            the minimum, too many increments...), ran past ``timeout`` or wrote no results;
            ``load_fraction`` is the load reached.
    """
    inp = Path(inp_path).resolve()
    if not inp.is_file():
        raise FileNotFoundError(f"input deck {inp} does not exist")
    exe = ccx_executable(executable)
    job = inp.with_suffix("")
    files = {s: job.with_suffix(s) for s in (".dat", ".frd", ".sta", ".cvg", ".log")}
    for s in (".dat", ".frd", ".sta", ".cvg"):
        files[s].unlink(missing_ok=True)
    env = dict(os.environ)
    nt = str(max(1, int(threads)))
    env.update(OMP_NUM_THREADS=nt, NUMBER_OF_CPUS=nt, CCX_NPROC_STIFFNESS=nt, CCX_NPROC_EQUATION_SOLVER=nt,
               CCX_NPROC_RESULTS=nt)
    t0 = time.perf_counter()
    with open(files[".log"], "w") as logf:
        try:
            proc = subprocess.run([exe, "-i", job.name], cwd=inp.parent, env=env, stdout=logf,
                                  stderr=subprocess.STDOUT, timeout=timeout, check=False)
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            rc = None
    seconds = time.perf_counter() - t0
    summary = read_sta(files[".sta"])
    text = files[".log"].read_text(errors="replace")
    run = CcxRun(inp, files[".dat"], files[".frd"], files[".sta"], files[".log"], seconds, summary,
                 residual_history(text))
    lines = text.splitlines()
    errors = [ln.strip() + (" " + lines[k + 1].strip() if k + 1 < len(lines) else "")
              for k, ln in enumerate(lines) if "*ERROR" in ln]
    if any("*ERROR reading" in e for e in errors):
        raise SolverSetupError(f"CalculiX could not read the input deck {inp}: {'; '.join(errors[:3])}")
    if rc is None:
        problem = f"did not finish within {timeout} s"
    elif errors or rc != 0:
        detail = "; ".join(errors[:3]) if errors else f"exit status {rc}"
        problem = f"stopped: {detail}"
    elif not files[".dat"].exists() or summary.load_fraction < 1.0 - 1e-9:
        problem = "wrote no results for the full load"
    else:
        log.debug("ccx %s: %d increments, %d iterations, %.1f s", inp.name, summary.increments, summary.iterations, seconds)
        return run
    raise ConvergenceError(
        f"CalculiX {problem} after {summary.increments} increments, at {100 * summary.load_fraction:.1f} % "
        f"of the load (see {files['.log']}); try smaller forces, a smaller initial/minimum increment or "
        "other fixed vertices",
        load_fraction=summary.load_fraction,
        result=run,
    )
