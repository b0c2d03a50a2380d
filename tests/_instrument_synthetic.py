"""A small surrogate with a tracked instrument, on the synthetic fields of the surrogate tests.

The fields are the nonlinear 3-parameter fields of ``_surrogate_synthetic`` plus, in 70 % of
the samples, a dent of the box's top face (z = 40 mm) under an instrument pushing straight down
at a random (x, y) by 0.5-3 mm: a local feature the markers (none near the top) barely see and
the instrument's pose gives away.
"""

import functools

import numpy as np

from tissuecast.instruments import InstrumentPose, ReferenceSurface
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.auxiliary import AuxiliaryInputs, AuxiliaryValues, InstrumentInput

from _surrogate_synthetic import MARKERS, box_mesh, nonlinear_fields

N = 900
SPLITS = {"train": np.arange(0, 600), "valid": np.arange(600, 700), "calibration": np.arange(700, 800),
          "test": np.arange(800, 900)}
INPUTS = AuxiliaryInputs((InstrumentInput("retractor", "RetractorToReference"),))
TOP = 40.0


def dent(points: np.ndarray, xy: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(B, n) mm downward displacement of the top face's dent under tips at ``xy`` (B, 2) mm pushed ``depth`` (B,) mm."""
    r2 = ((points[None, :, :2] - xy[:, None, :]) ** 2).sum(-1)
    return np.exp(-r2 / 20.0) * np.exp(-(TOP - points[None, :, 2]) / 5.0) * depth[:, None]


@functools.lru_cache(maxsize=None)
def instrument_data():
    """(mesh, fields (N, n, 3) mm, poses (N,) InstrumentPose, inputs (N, 8))."""
    mesh = box_mesh()
    rng = np.random.default_rng(1)
    U = nonlinear_fields(mesh, rng.uniform(-1, 1, (N, 3)))
    contact = rng.random(N) < 0.7
    xy = rng.uniform([3.0, 3.0], [17.0, 22.0], (N, 2))
    depth = rng.uniform(0.5, 3.0, N)
    U[:, :, 2] -= dent(mesh.points, xy, depth) * contact[:, None]
    surface = ReferenceSurface.of(mesh)
    poses = tuple(surface.pose(np.r_[p, TOP - h], [0.0, 0.0, -1.0]) if c else InstrumentPose.away()
                  for p, h, c in zip(xy, depth, contact))
    return mesh, U, poses, np.array([p.features() for p in poses])


@functools.lru_cache(maxsize=None)
def instrument_model() -> DeformationModel:
    """Trained with the instrument (and its markers-only fallback), trust layer included."""
    mesh, U, _, A = instrument_data()
    m = DeformationModel(epochs=150, patience=0, batch_size=64, n_components=16, hidden=(64, 32))
    return m.fit(U, MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
                 calibration_idx=SPLITS["calibration"], auxiliary=AuxiliaryValues(INPUTS, A))
