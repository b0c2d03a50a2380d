"""Smooth synthetic deformations and a quickly trained model, for exercising the serving path.

Benchmarks, examples and tests of the OpenIGTLink server need *a* trained
:class:`~tissuecast.surrogate.DeformationModel` of the right size without running the FEM
data-set generator. The fields made here are smooth (polynomial of degree <= 2 in the
normalised coordinates, with a mild quadratic coupling of the weights so the map from
marker to field is nonlinear), vanish nowhere in particular, and are scaled to a chosen
peak displacement. They are *not* a substitute for simulated tissue mechanics: use them to
test plumbing and speed, never to judge accuracy.
"""

from __future__ import annotations

import numpy as np

__all__ = ["synthetic_fields", "synthetic_model"]


def _modes(points: np.ndarray) -> np.ndarray:
    """(n, 10) monomials of degree <= 2 of the normalised coordinates."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    x, y, z = ((points - (lo + hi) / 2) / np.maximum(hi - lo, 1e-9) * 2).T
    return np.stack([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, y * z, z * x], axis=1)


def synthetic_fields(mesh, n_samples: int, *, peak: float = 10.0, seed: int = 0) -> np.ndarray:
    """Random smooth displacement fields on a mesh.

    Args:
        mesh: a :class:`~tissuecast.mesh.TetMesh` with n vertices (mm).
        n_samples: N, number of fields.
        peak: mm, the largest vertex displacement over the whole set.
        seed: random seed.

    Returns:
        (N, n, 3) float64 displacements, mm.
    """
    rng = np.random.default_rng(seed)
    modes = _modes(np.asarray(mesh.points, dtype=np.float64))  # (n, 10)
    weights = rng.uniform(-1.0, 1.0, size=(n_samples, modes.shape[1], 3))
    # nonlinear coupling: the quadratic modes also respond to the square of the linear ones
    weights[:, 4:7, :] += 0.5 * weights[:, 1:4, :] ** 2
    fields = np.einsum("nm,smc->snc", modes, weights)
    fields *= peak / np.abs(fields).max()
    return fields


def synthetic_model(mesh, *, n_samples: int = 200, n_markers: int = 5, peak: float = 10.0, seed: int = 0, **config):
    """A small :class:`~tissuecast.surrogate.DeformationModel` fitted on :func:`synthetic_fields`.

    Args:
        mesh: the mesh to predict on.
        n_samples: size of the synthetic training set (10 % of it validates).
        n_markers: markers chosen with :func:`tissuecast.markers.select_markers`
            (start vertex 0, minimum distance shrunk until enough markers fit).
        peak: mm, largest displacement in the set.
        seed: seed of the fields and of training.
        **config: ``SurrogateConfig`` overrides; defaults here are small and fast
            (``n_components=8, hidden=(32, 32), epochs=60, patience=0``).

    Returns:
        The fitted model.
    """
    from ..markers import select_markers
    from ..surrogate import DeformationModel

    fields = synthetic_fields(mesh, n_samples, peak=peak, seed=seed)
    extent = float(np.max(np.ptp(np.asarray(mesh.points), axis=0)))
    distance = extent / 4
    while True:
        try:
            markers = select_markers(mesh, count=n_markers, start=0, min_distance=distance)
            break
        except ValueError:
            if distance < 1e-3 * extent:
                raise
            distance /= 2
    options = dict(n_components=8, hidden=(32, 32), epochs=60, patience=0, seed=seed)
    options.update(config)
    return DeformationModel(**options).fit(fields, markers, mesh=mesh)
