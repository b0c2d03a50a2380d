"""What a paper-size run costs on a mesh, told before it starts.

A paper-size run is ``configs/paper.toml`` on the mesh: 2000 LBO + 200 test-2 samples,
quadratic (10-node) tetrahedra, two workers, then training and evaluation. Its wall-clock
time was measured end to end on meshes of three sizes (docs/scaling.md, "Large meshes and the
scaling exponent": the phantom, the phantom re-meshed at 0.66 of its sizes, and at 0.44,
whose sample phase was measured in part and projected). :func:`paper_run_estimate` fits a
power law ``t = t_1 (n / n_1)^b`` through those runs by least squares in log-log space (n the
vertex count, ``n_1`` and ``t_1`` the first run) and evaluates it at the mesh's vertex count;
more than 5 % outside the measured range it extrapolates, and says so. Times are for the idle 2-core
machine the runs were measured on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["PAPER_RUNS", "PAPER_SAMPLES", "RunEstimate", "paper_run_estimate", "duration_text"]

#: (vertices, wall-clock seconds) of paper-size runs, from docs/scaling.md (the last one's
#: sample phase projected from its first 321 samples)
PAPER_RUNS = ((1169, 265.0), (3515, 1134.0), (11045, 5700.0))
#: samples of a paper-size run: LBO (train + valid + test-1) and test-2
PAPER_SAMPLES = (2000, 200)


@dataclass(frozen=True)
class RunEstimate:
    """The expected cost of a paper-size run on one mesh.

    Attributes:
        n_vertices: the mesh's vertices.
        unknowns: displacement unknowns with quadratic tetrahedra, 3 (vertices + edges).
        seconds: expected wall-clock time on the reference machine, s.
        exponent: b of the fitted power law t ~ n^b.
        extrapolated: the mesh lies more than 5 % outside the vertex range of the measured runs.
    """

    n_vertices: int
    unknowns: int
    seconds: float
    exponent: float
    extrapolated: bool

    def text(self) -> str:
        """One line for people: the time, the unknowns and where the figure comes from."""
        lbo, test2 = PAPER_SAMPLES
        outside = "; an extrapolation beyond the measured meshes" if self.extrapolated else ""
        low, high = PAPER_RUNS[0][0], PAPER_RUNS[-1][0]
        return (f"a paper-size run ({lbo} + {test2} samples, quadratic elements, {self.unknowns:,} unknowns) "
                f"would take about {duration_text(self.seconds)} on 2 workers (power law t ~ n^{self.exponent:.2f} "
                f"fitted to the paper-preset runs on {low}-{high} vertices in docs/scaling.md{outside})")


def _fit() -> tuple[float, float]:
    """(log t at n_1, exponent b) of the least-squares line through log t against log (n / n_1)."""
    n = np.array([r[0] for r in PAPER_RUNS], dtype=np.float64)
    t = np.array([r[1] for r in PAPER_RUNS], dtype=np.float64)
    b, a = np.polyfit(np.log(n / n[0]), np.log(t), 1)
    return float(a), float(b)


def paper_run_estimate(n_vertices: int, n_edges: int) -> RunEstimate:
    """Expected wall-clock time of a paper-size run on a mesh (module notes).

    Args:
        n_vertices: the mesh's vertices.
        n_edges: its edges (the mid-edge nodes of quadratic elements).
    """
    a, b = _fit()
    seconds = math.exp(a) * (n_vertices / PAPER_RUNS[0][0]) ** b
    extrapolated = not 0.95 * PAPER_RUNS[0][0] <= n_vertices <= 1.05 * PAPER_RUNS[-1][0]
    return RunEstimate(int(n_vertices), 3 * int(n_vertices + n_edges), float(seconds), b, extrapolated)


def duration_text(seconds: float) -> str:
    """A duration for people: ``"45 s"``, ``"32 min"``, ``"2.4 h"``, ``"3.1 days"``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"
