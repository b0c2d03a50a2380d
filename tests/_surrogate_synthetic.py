"""Synthetic data for the surrogate/evaluation tests: a box mesh and nonlinear displacement fields.

The fields are a nonlinear function of 3 latent parameters, so marker displacements determine
them but not linearly (an MLP can beat the ridge baseline).
"""

import numpy as np

from tissuecast.mesh import TetMesh

MARKERS = np.array([3, 50, 120, 200, 260])
#: How far (mm) the compiled predictor's fields may lie from the float64 forward pass: it
#: multiplies its hidden layers and its decode in float32 (``tissuecast.surrogate.fastpath.DTYPE``),
#: whose rounding of the synthetic fields here (tens of mm) is of order 1e-6 mm.
COMPILED_ATOL = 1e-5


def box_mesh(nx=4, ny=5, nz=8, h=5.0) -> TetMesh:
    """A 20 x 25 x 40 mm box of Kuhn-split cubes (270 vertices)."""
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1).reshape(-1, 3)
    vid = lambda i, j, k: (i * (ny + 1) + j) * (nz + 1) + k  # noqa: E731
    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    tets = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                c = [vid(i + a, j + b, k + e) for a in (0, 1) for b in (0, 1) for e in (0, 1)]
                tets += [[c[v] for v in t] for t in kuhn]
    return TetMesh(g * h * 1.0, np.array(tets))


def nonlinear_fields(mesh: TetMesh, theta: np.ndarray) -> np.ndarray:
    """(N, n, 3) mm fields from latent parameters theta (N, 3) in about [-1, 1]."""
    X = mesh.points / mesh.extent.max()
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    t0, t1, t2 = theta[:, 0:1], theta[:, 1:2], theta[:, 2:3]
    ux = 8 * t0 * z**2 + 4 * t1 * t2 * np.sin(np.pi * y) + 2 * np.tanh(3 * t2) * x
    uy = 6 * np.sin(t0 + 2 * t1) * x * z + 3 * t2**2
    uz = 5 * t2 * z + 3 * t0 * t1 - 2 * np.cos(2 * t0) * y
    return np.stack([ux, uy, uz], -1)


class FakeDataset:
    """In-memory stand-in with the attributes of :class:`tissuecast.dataset.Dataset`.

    ``n`` LBO-like samples split 8:1:1 plus ``n_test2`` shifted samples with beta labels;
    sample 5 is marked failed (NaN displacements).
    """

    SPLITS = {"train": 0, "valid": 1, "test1": 2, "test2": 3}

    def __init__(self, n=300, n_test2=44, seed=0):
        rng = np.random.default_rng(seed)
        self.mesh = box_mesh()
        theta = rng.uniform(-1, 1, (n, 3))
        betas = np.repeat(np.linspace(0, 1, 11), max(1, n_test2 // 11))[:n_test2]
        theta2 = rng.uniform(-1, 1, (n_test2, 3)) * (1.1 - 0.1 * betas[:, None])
        self.displacements = nonlinear_fields(self.mesh, np.vstack([theta, theta2])).astype(np.float32)
        n_tr, n_va = int(0.8 * n), int(0.1 * n)
        codes = np.r_[np.zeros(n_tr), np.ones(n_va), np.full(n - n_tr - n_va, 2), np.full(n_test2, 3)].astype(np.int8)
        self.split_codes = codes
        names = np.array(list(self.SPLITS))
        self.split = names[codes]
        self.status = np.ones(len(codes), np.int8)
        self.status[5] = 2
        self.displacements[5] = np.nan
        self.beta = np.r_[np.full(n, np.nan), betas]
        self.markers = MARKERS.copy()
        self.fixed = np.array([0, 1, 2])
        self.config = None
        self.path = None  # in memory: no store
        self.scenario = None  # not recorded
        self.scenario_arrays = {}  # nothing resolved: no attached extent drawn
        self.n_samples = len(codes)

    def select(self, split=None, status="done"):
        keep = np.ones(self.n_samples, bool)
        if split is not None:
            keep &= self.split_codes == self.SPLITS[split]
        if status is not None:
            keep &= self.status == {"pending": 0, "done": 1, "failed": 2}[status]
        return np.flatnonzero(keep)

    def __repr__(self):
        return f"FakeDataset({self.n_samples} samples)"


def smooth_solver_factory(scenario, cfg):
    """A fast stand-in for the FEM solver (for pipeline tests): forces are smoothed over the
    mesh graph and passed through a mild nonlinearity, u = s + 0.05 |s| s (mm)."""
    from types import SimpleNamespace

    import scipy.sparse as sp

    mesh, fixed = scenario.mesh, scenario.supported
    A = mesh.vertex_adjacency.astype(float)
    deg = np.asarray(A.sum(axis=1)).ravel()
    P = sp.diags(1.0 / (deg + 1.0)) @ (A + sp.eye(mesh.n_vertices))

    def make(solver_cfg):
        def solve(forces, initial_guess=None, time_limit=None):
            s = np.asarray(forces, dtype=float) * 20.0
            for _ in range(15):
                s = P @ s
            s[np.asarray(fixed)] = 0.0
            u = s + 0.05 * np.linalg.norm(s, axis=1, keepdims=True) * s
            return SimpleNamespace(displacement=u, increments=1, iterations=1, factorizations=1)

        return SimpleNamespace(solve=solve)

    return make


def write_box_config(folder, n_samples=120, n_test2=12):
    """A TOML config for the pipeline tests: the box mesh as .vtu, 4 markers, P1, fixed alpha."""
    from pathlib import Path

    import meshio

    from tissuecast.config import Config, config_to_toml, with_overrides

    folder = Path(folder)
    mesh = box_mesh()
    meshio.Mesh(mesh.points, [("tetra", mesh.tets)]).write(folder / "box.vtu")
    cfg = with_overrides(
        Config(),
        name="box", output=str(folder / "run"),
        mesh={"path": str(folder / "box.vtu")},
        markers={"start": 0, "min_distance": 5.0, "count": 4, "fixed_count": 3},
        solver={"order": 1},
        forces={"n_basis": 8, "betas": [0.0, 0.5, 1.0], "target_max_displacement": 10.0},
        dataset={"store": str(folder / "ds.zarr"), "n_samples": n_samples, "n_test2": n_test2, "workers": 1,
                 "alpha": 1.0, "calibration_samples": 2, "seed": 3},
        surrogate={"epochs": 60, "patience": 0, "n_components": 6, "ensemble": 2},
        evaluate={"renders": 1},
    )
    path = folder / "box.toml"
    path.write_text(config_to_toml(cfg))
    return path


def simulate_box_store(folder, **kwargs):
    """Write the box config into ``folder`` and simulate its store with the stand-in solver.

    Returns:
        ``(config path, Config)``; the store is ``Config.dataset.store``.
    """
    from tissuecast.config import load_config
    from tissuecast.dataset import simulate

    cfg_path = write_box_config(folder, **kwargs)
    cfg = load_config(cfg_path)
    simulate(cfg, progress=False, solver_factory="_surrogate_synthetic:smooth_solver_factory")
    return cfg_path, cfg
