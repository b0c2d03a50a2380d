"""Random surface force fields: the LBO basis and training fields, and test-2 (LSC) fields.

All forces are dead nodal loads in N, arrays of shape (n_vertices, 3), zero off the surface.
"""

from .fields import field_scale, lbo_field, random_lbo_weights
from .lbo import LBOBasis, lbo_basis, surface_operator
from .lsc import blend, lsc_field, smooth, surface_graph_laplacian
from .traction import traction_loads

__all__ = [
    "LBOBasis",
    "lbo_basis",
    "surface_operator",
    "random_lbo_weights",
    "lbo_field",
    "field_scale",
    "surface_graph_laplacian",
    "smooth",
    "lsc_field",
    "blend",
    "traction_loads",
]
