"""``tissuecast export-inp MESH OUT.inp``: write the FEM problem as a CalculiX/Abaqus input deck.

The deck holds the mesh (C3D10 or C3D4), the neo-Hookean material, the fixed vertices and the
nodal forces of the configuration; run it with ``ccx -i OUT`` (without ``.inp``) or Abaqus.
Node ids in the deck are 1-based: vertex i (0-based) is node i + 1. Units: mm, N, MPa.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import load_config
from ..errors import ConfigError

#: RMS surface nodal force (N) of the example field written when no --forces file is given
#: (about 25 mm of displacement on the phantom with the default fixed vertices).
EXAMPLE_RMS_FORCE = 0.004


def register(sub) -> None:
    p = sub.add_parser(
        "export-inp",
        help="write the FEM problem as a CalculiX/Abaqus input deck (.inp)",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
    )
    p.add_argument("mesh", help="mesh file (any format tissuecast reads) or 'phantom' for the built-in phantom")
    p.add_argument("out", help="output .inp file")
    p.add_argument("--config", metavar="FILE", help="TOML config (markers, fixed vertices, material, solver order)")
    p.add_argument("--forces", metavar="FILE", help="(n, 3) nodal forces in N: .npy, or .csv with 3 columns "
                   "(one row per vertex, 0-based order); default: a random smooth LBO example field")
    p.add_argument("--order", type=int, choices=(1, 2), help="element order (default: the config's solver.order)")
    p.add_argument("--seed", type=int, default=0, help="seed of the example force field (default 0)")
    p.add_argument("--force-rms", type=float, default=EXAMPLE_RMS_FORCE, metavar="N",
                   help=f"RMS surface nodal force of the example field in N (default {EXAMPLE_RMS_FORCE})")
    p.add_argument("--initial-increment", type=float, default=0.05, help="first load increment (fraction, default 0.05)")
    p.add_argument("--max-increment", type=float, default=0.25, help="largest load increment (fraction, default 0.25)")
    p.set_defaults(func=run)


def _read_forces(path: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"forces file {p} does not exist")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        return np.load(p, allow_pickle=False)
    if suffix in (".csv", ".txt"):
        first = p.read_text().lstrip().split("\n", 1)[0]
        skip = 0 if first and (first[0].isdigit() or first[0] in "+-.") else 1
        try:
            return np.loadtxt(p, delimiter=",", skiprows=skip, ndmin=2)
        except ValueError as exc:
            raise ConfigError(f"could not read forces from {p}: {exc}; expected 3 comma-separated numbers per row") from None
    raise ConfigError(f"forces file {p} must be .npy or .csv (n rows of fx, fy, fz in N), got {suffix!r}")


def _example_forces(mesh, cfg, seed: int, rms: float) -> np.ndarray:
    from ..forces import field_scale, lbo_basis, lbo_field, random_lbo_weights

    basis = lbo_basis(mesh, n=cfg.forces.n_basis)
    weights = random_lbo_weights(np.random.default_rng(seed), basis.n_vectors)
    return lbo_field(basis, weights, rms / field_scale(basis), mesh.n_points)


def run(args) -> int:
    from ..fem import build_problem
    from ..fem.calculix import write_inp
    from ..markers import markers_and_fixed
    from .mesh_cmd import PHANTOM_WORD, load_mesh_argument

    cfg = load_config(args.config)
    mesh = load_mesh_argument(args.mesh, units=cfg.mesh.units, mesh_size=cfg.mesh.surface_mesh_size, mesh_config=cfg.mesh)
    markers, fixed = markers_and_fixed(mesh, cfg.markers)
    forces = _read_forces(args.forces) if args.forces else _example_forces(mesh, cfg, args.seed, args.force_rms)
    problem = build_problem(mesh, cfg, fixed, order=args.order)
    order, material = problem.order, problem.material
    out = write_inp(
        args.out, mesh, material, fixed, forces, order=order, node_sets={"MARKERS": markers},
        initial_increment=args.initial_increment, max_increment=max(args.max_increment, args.initial_increment),
        title=f"{cfg.name}: {args.mesh if args.mesh == PHANTOM_WORD else Path(args.mesh).name}, "
              f"E={material.youngs_modulus} MPa, nu={material.poisson_ratio}",
    )
    print(f"wrote {out}: {mesh.n_points} vertices, {mesh.n_tets} {'C3D10' if order == 2 else 'C3D4'} elements, "
          f"fixed vertices {fixed.tolist()} (0-based; nodes {(fixed + 1).tolist()} in the deck), "
          f"markers {markers.tolist()} (node set MARKERS), max |force| {np.linalg.norm(forces, axis=1).max():.4g} N")
    print(f"run it with: cd {out.resolve().parent} && ccx -i {out.stem}")
    return 0
