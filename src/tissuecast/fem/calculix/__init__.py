"""CalculiX / Abaqus interoperability: write the FEM problem as an input deck, run ``ccx``, read
the displacements back.

The deck uses only keywords that CalculiX 2.20 and Abaqus/Standard both read: ``*NODE``,
``*ELEMENT, TYPE=C3D10`` (or ``C3D4``), ``*HYPERELASTIC, NEO HOOKE``, ``*STEP, NLGEOM=YES``
with automatic incrementation (``*STATIC``), ``*BOUNDARY``, ``*CLOAD`` (dead loads) and
``*NODE PRINT`` / ``*NODE FILE`` for the displacements; for scenarios (:class:`DeckScenario`)
also ``SPRING1`` elements with ``*SPRING`` / ``*ORIENTATION``, ``*DENSITY`` with ``*DLOAD, GRAV`` and one
``*SOLID SECTION`` per material region.

Numbering: decks are 1-based. Mesh vertex ``i`` (0-based) is node ``i + 1``; the mid-edge
node of ``mesh.edges[e]`` (quadratic elements) is node ``n + e + 1``, so node ``k`` is row
``k - 1`` of ``mesh.points10``. Units: mm, N, MPa.

This is also a second backend for data generation (:func:`solve_calculix`) for users who
trust CalculiX more than the built-in solver.
"""

from ._backend import solve_calculix
from ._deck import write_inp
from ._scenario import DeckScenario
from ._results import StaSummary, read_displacements, read_sta
from ._runner import CcxRun, ccx_executable, run_ccx

__all__ = [
    "write_inp",
    "DeckScenario",
    "ccx_executable",
    "run_ccx",
    "CcxRun",
    "read_displacements",
    "read_sta",
    "StaSummary",
    "solve_calculix",
]
