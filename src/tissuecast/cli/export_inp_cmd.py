"""``tissuecast export-inp MESH OUT.inp``: write the FEM problem as a CalculiX/Abaqus input deck.

The deck holds the mesh (C3D10 or C3D4), the neo-Hookean material(s), the supports and the
loads of one sample of the configuration's scenario: pinned vertices and the attached region
(``*BOUNDARY``), the elastic support (``SPRING1`` elements), the LBO forces (``*CLOAD``; as
consistent traction loads with forces.loading = "traction"), the gravity change (``*DENSITY`` and
``*DLOAD, GRAV``), the indentation (``*BOUNDARY`` with values) and per-region materials. Run it
with ``ccx -i OUT`` (without ``.inp``) or Abaqus. MESH may also be a data-set store: the deck is
then its sample ``--sample`` (stored forces, the scenario draws of the sample's seed). Node ids
in the deck are 1-based: vertex i (0-based) is node i + 1. Units: mm, N, MPa, t/mm^3.
"""

from __future__ import annotations

import dataclasses

from pathlib import Path

import numpy as np

from ..config import with_overrides
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
    p.add_argument("mesh", help="mesh file (any format tissuecast reads), 'phantom' for the built-in phantom, or a "
                   "data-set store (.zarr folder) whose sample --sample to write")
    p.add_argument("out", help="output .inp file")
    p.add_argument("--config", metavar="FILE",
                   help="TOML config or a packaged preset (markers, fixed vertices, material, solver order)")
    p.add_argument("--forces", metavar="FILE", help="(n, 3) nodal forces in N: .npy, or .csv with 3 columns "
                   "(one row per vertex, 0-based order); default: a random smooth LBO example field")
    p.add_argument("--order", type=int, choices=(1, 2), help="element order (default: the config's solver.order)")
    p.add_argument("--seed", type=int, default=0, help="sample seed: of the example force field and the scenario's "
                   "draws (gravity direction, indentation), as a data set's sample with this seed (default 0)")
    p.add_argument("--sample", type=int, default=0, metavar="K", help="with a data-set store: its sample K (0-based)")
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
    return lbo_field(basis, weights, rms / field_scale(basis), mesh.n_vertices)


def _from_store(args):
    """``(config, mesh, markers, scenario, forces (n, 3) N, sample seed)`` of a store's sample."""
    from ..dataset import open_dataset
    from ..scenario import restore_scenario

    ds = open_dataset(args.mesh)
    if not 0 <= args.sample < len(ds):
        raise ConfigError(f"--sample {args.sample} is outside 0..{len(ds) - 1} (0-based) of {args.mesh}")
    cfg, mesh = ds.config, ds.mesh
    scenario = restore_scenario(mesh, cfg, ds.scenario_arrays, ds.basis)
    forces = np.asarray(ds.forces[args.sample], dtype=np.float64)
    return cfg, mesh, np.asarray(ds.markers), scenario, forces, int(ds.seed[args.sample])


def _from_config(args):
    """``(config, mesh, markers, scenario, forces (n, 3) N, sample seed)`` from a mesh and a config."""
    from ..mesh.tags import mesh_file_tags
    from ..scenario import build_scenario, scenario_markers
    from .mesh_cmd import PHANTOM_WORD, load_mesh_argument
    from ..app.configuration import load_run_config

    cfg = load_run_config(args.config)
    if args.order is not None:
        cfg = with_overrides(cfg, solver={"order": args.order})
    mesh = load_mesh_argument(args.mesh, units=cfg.mesh.units, mesh_size=cfg.mesh.surface_mesh_size, mesh_config=cfg.mesh)
    tags = mesh_file_tags(None if args.mesh == PHANTOM_WORD else args.mesh)
    markers, fixed = scenario_markers(mesh, cfg, tags)
    scenario = build_scenario(mesh, cfg, fixed, tags, material_seed=cfg.dataset.seed)
    forces = _read_forces(args.forces) if args.forces else _example_forces(mesh, cfg, args.seed, args.force_rms)
    if forces.shape != (mesh.n_vertices, 3) or not np.all(np.isfinite(forces)):
        raise ConfigError(f"forces must be finite numbers of N with shape ({mesh.n_vertices}, 3) (one row per vertex, "
                          f"0-based order), got shape {forces.shape}")
    return cfg, mesh, markers, scenario, forces, args.seed


def run(args) -> int:
    from ..fem.calculix import DeckScenario, write_inp

    is_store = Path(args.mesh).is_dir()
    if is_store and (args.config or args.order or args.forces):
        raise ConfigError("a data-set store carries its own config, element order and forces; leave out --config, "
                          "--order and --forces")
    cfg, mesh, markers, scenario, forces, seed = (_from_store if is_store else _from_config)(args)
    if not cfg.scenario.lbo_forces:
        forces = np.zeros_like(forces)
    inputs = scenario.inputs_for(seed, forces)
    draw, params = inputs.draw, inputs.parameters
    problem = scenario.problem()
    changes = {k: v for k, v in zip(("materials", "springs"), inputs.solver_parameters) if v is not None}
    problem = dataclasses.replace(problem, **changes) if changes else problem
    order, material = problem.order, problem.material
    surface = inputs.surface
    if cfg.forces.loading == "nodal":
        surface = surface[: mesh.n_vertices]
    density = acceleration = None
    if draw.body_force is not None:  # *DLOAD, GRAV: the same consistent loads as the solver's body loads
        density = cfg.scenario.gravity.density * (1.0 if params is None else params.density)
        acceleration = draw.body_force / cfg.scenario.gravity.density
    ids, values = inputs.prescribed_ids, inputs.prescribed_values
    fixed = scenario.supported
    sets = {"MARKERS": markers}
    if draw.indentation is not None:
        sets["INDENT"] = draw.indentation.vertices
    if len(ids) and params is not None:  # the attached region's drawn extent beyond its smallest, held at zero
        band = ids[~np.isin(ids, sets.get("INDENT", []))]
        if len(band):
            sets["ATTACHED_EXTENT"] = band
    source = args.mesh if args.mesh == "phantom" else Path(args.mesh).name
    out = write_inp(
        args.out, mesh, material, fixed, surface, order=order, node_sets=sets,
        prescribed=(ids, values) if len(ids) else None,
        scenario=DeckScenario.from_problem(problem, density, acceleration),
        initial_increment=args.initial_increment, max_increment=max(args.max_increment, args.initial_increment),
        title=f"{cfg.name}: {source}{f' sample {args.sample}' if is_store else ''}, scenario {cfg.scenario.name}, "
              f"E={material.youngs_modulus} MPa, nu={material.poisson_ratio}",
    )
    print(f"wrote {out}: {mesh.n_vertices} vertices, {mesh.n_tets} {'C3D10' if order == 2 else 'C3D4'} elements, "
          + (f"fixed vertices {fixed.tolist()} (0-based; nodes {(fixed + 1).tolist()} in the deck), " if len(fixed) <= 10
             else f"{len(fixed)} fixed vertices (0-based id i is node i + 1 in the deck, node set NFIXED), ")
          + f"markers {markers.tolist()} "
          f"(node set MARKERS), max |force| {np.linalg.norm(forces, axis=1).max():.4g} N")
    print(f"scenario {cfg.scenario.name!r} (sample seed {seed}): " + ", ".join(_deck_parts(scenario, draw)))
    if params is not None:
        print("drawn parameters (in the deck: materials, springs, density, attached extent held at zero): "
              + ", ".join(f"{k} {v:.4g}" for k, v in params.record().items()))
    print(f"run it with: cd {out.resolve().parent} && ccx -i {out.stem}")
    return 0


def _deck_parts(scenario, draw) -> list[str]:
    parts = [f"{len(scenario.pinned)} pins", f"{len(scenario.attached)} attached vertices"]
    if scenario.springs is not None:
        parts.append(f"springs at {len(scenario.springs)} nodes (SPRING1)")
    if draw.body_force is not None:
        parts.append(f"gravity change {np.linalg.norm(draw.body_force):.3g} N/mm^3 (*DLOAD, GRAV)")
    if draw.indentation is not None:
        ind = draw.indentation
        parts.append(f"indentation of {len(ind.vertices)} vertices by {np.linalg.norm(ind.displacement):.3g} mm "
                     "(*BOUNDARY values, node set INDENT)")
    if scenario.materials is not None:
        parts.append(f"{len(np.unique(scenario.materials.region))} material groups")
    return parts

