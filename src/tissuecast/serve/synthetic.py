"""Smooth synthetic deformations and a quickly trained model, for exercising the serving path.

Benchmarks, examples and tests of the OpenIGTLink server need *a* trained
:class:`~tissuecast.surrogate.DeformationModel` of the right size without running the FEM
data-set generator. The fields made here are smooth (polynomial of degree <= 2 in the
normalised coordinates), driven by a few latent parameters through a mildly nonlinear map,
and scaled to a chosen peak displacement. They are *not* a substitute for simulated tissue mechanics: use them to
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


def synthetic_fields(mesh, n_samples: int, *, peak: float = 10.0, latent: int = 6, seed: int = 0) -> np.ndarray:
    """Random smooth displacement fields on a mesh, driven by a few latent parameters.

    Each field is ``modes @ W(z)``: 10 polynomial modes (degree <= 2) per axis, weighted by
    ``W(z) = A z + (z B z)`` for latent ``z ~ U(-1, 1)^latent``, with fixed mixing matrices A
    and B (the same for every seed). A few latent parameters, like the few force patterns of
    a real tissue sample, keep the field recoverable from a handful of markers; B makes the
    marker-to-field map nonlinear.

    Args:
        mesh: a :class:`~tissuecast.mesh.TetMesh` with n vertices (mm).
        n_samples: N, number of fields.
        peak: mm, about the largest vertex displacement (fixed scale, independent of N).
        latent: number of latent parameters.
        seed: random seed of the latent draws.

    Returns:
        (N, n, 3) float64 displacements, mm.
    """
    modes = _modes(np.asarray(mesh.points, dtype=np.float64))  # (n, 10)
    structure = np.random.default_rng(20201119)
    A = structure.normal(size=(latent, modes.shape[1] * 3))
    B = structure.normal(size=(latent, latent, modes.shape[1] * 3)) * (0.5 / latent)

    def fields_of(z: np.ndarray) -> np.ndarray:
        w = z @ A + np.einsum("si,sj,ijk->sk", z, z, B)
        return np.einsum("nm,smc->snc", modes, w.reshape(len(z), modes.shape[1], 3))

    scale = peak / np.abs(fields_of(structure.uniform(-1.0, 1.0, size=(256, latent)))).max()
    z = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n_samples, latent))
    return fields_of(z) * scale


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
