"""Pictures and files that show a scenario: supports, regions, gravity, indentation sites.

:func:`preview_arrays` gathers what to show as plain arrays (one value per vertex or per
element); :func:`write_preview_vtu` writes them next to the mesh for ParaView or 3D Slicer
(coordinates in mm, in the mesh's own frame); :func:`render_preview` draws them off-screen with
pyvista (extra ``viz``).

Support codes (point data ``support``): 0 free surface or interior, 1 elastic support (spring
region), 2 attached region, 3 pinned vertex.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import require
from .scenario import Scenario, ScenarioDraw

__all__ = ["SUPPORT_CODES", "preview_arrays", "write_preview_vtu", "render_preview", "example_deformations",
           "example_alpha",
           "scenario_places"]

#: Without a fixed ``dataset.alpha``, the example LBO fields are scaled so that their median
#: linear (small-strain) peak is this share of ``forces.target_max_displacement``: the
#: nonlinear response of a body on pins grows faster than linearly, so a full-size linear
#: guess would overshoot.
LINEAR_AIM = 0.3

SUPPORT_CODES = {"free": 0, "springs": 1, "attached": 2, "pinned": 3}


def preview_arrays(sc: Scenario, draws: list[ScenarioDraw]) -> tuple[dict, dict]:
    """Point and cell data describing a scenario and example draws.

    Returns:
        ``(point_data, cell_data)``: point data ``support`` (n,) int (:data:`SUPPORT_CODES`),
        ``spring_normal_stiffness`` (n,) N/mm^3 (0 off the spring region),
        ``indentation_example`` (n,) int (k = vertex of example k's patch, 1-based; 0 none),
        ``indentation_displacement`` (n, 3) mm and ``body_force_example`` (n, 3) N/mm^3 of
        the first example, ``indentation_access`` (n,) int (1 = in the surgical access region
        where patch centres may be drawn); cell data ``material_region`` (m,) int (-1 = the default material)
        and, with material regions, ``youngs_modulus`` (m,) MPa and ``poisson_ratio`` (m,).
    """
    mesh = sc.mesh
    n = mesh.n_vertices
    support = np.zeros(n, dtype=np.int32)
    support[sc.spring_region] = SUPPORT_CODES["springs"]
    support[sc.attached] = SUPPORT_CODES["attached"]
    support[sc.pinned] = SUPPORT_CODES["pinned"]
    stiffness = np.zeros(n)
    if sc.springs is not None:
        stiffness[sc.spring_region] = sc.config.springs.normal_stiffness
    example = np.zeros(n, dtype=np.int32)
    push = np.zeros((n, 3))
    for k, d in enumerate(draws):
        if d.indentation is not None:
            example[d.indentation.vertices] = k + 1
            if k == 0:
                push[d.indentation.vertices] = d.indentation.displacement
    body = np.zeros((n, 3))
    if draws and draws[0].body_force is not None:
        body[:] = draws[0].body_force
    access = np.zeros(n, dtype=np.int32)
    if sc.sites is not None:
        access[sc.sites.access] = 1
    point = {"support": support, "spring_normal_stiffness": stiffness, "indentation_example": example,
             "indentation_displacement": push, "body_force_example": body, "indentation_access": access}
    if sc.materials is not None:
        cell = {"youngs_modulus": sc.materials.youngs_modulus, "poisson_ratio": sc.materials.poisson_ratio,
                "material_region": sc.materials.region.astype(np.int32)}
    else:
        cell = {"material_region": np.full(mesh.n_tets, -1, dtype=np.int32)}
    return point, cell


def scenario_places(sc: Scenario) -> dict[str, np.ndarray]:
    """The places the scenario's region rules found on its mesh: ``"attached"``, ``"springs"`` and
    ``"access"`` (the indentation's surgical access, when on) -> (k,) vertex ids of a ``markups``
    rule's snapped points or an ``extreme`` rule's vertex (:func:`~.regions.region_anchors`);
    rules without a single place are left out."""
    from .regions import region_anchors

    rules = {"attached": (sc.config.attached, "scenario.attached"), "springs": (sc.config.springs, "scenario.springs")}
    if sc.sites is not None:
        rules["access"] = (sc.config.indentation.access, "scenario.indentation.access")
    places = {name: region_anchors(sc.mesh, rule, key) for name, (rule, key) in rules.items()}
    return {name: ids for name, ids in places.items() if ids.size}


def example_alpha(sc: Scenario, config, seeds, solver=None) -> float:
    """The examples' surface field magnitude, N: ``dataset.alpha``, or if 0 :data:`LINEAR_AIM` of
    ``forces.target_max_displacement`` by the median linear response of the fields of ``seeds``."""
    if config.dataset.alpha > 0:
        return float(config.dataset.alpha)
    if solver is None:
        from ..fem import Solver

        solver = Solver(sc.problem(), config.solver)
    reference, free = solver.reference_factor(), solver.free_dofs
    peaks = []
    for seed in seeds:
        loads = sc.loads(ScenarioDraw(), sc.surface_forces.field(seed, 1.0)[0], config.forces.loading)
        u = np.zeros(loads.size)
        u[free] = reference.solve(loads.ravel()[free])
        peaks.append(float(np.linalg.norm(u.reshape(-1, 3)[: sc.mesh.n_vertices], axis=1).max()))
    return LINEAR_AIM * config.forces.target_max_displacement / max(float(np.median(peaks)), 1e-300)


def example_deformations(sc: Scenario, config, seeds) -> list[tuple[str, np.ndarray]]:
    """Solve the samples ``seeds`` of the scenario with the built-in solver (one Newton solve each).

    Each sample's loads are a data set's: its LBO field (weights from ``default_rng(seed)``;
    magnitude ``dataset.alpha``, or if 0 :data:`LINEAR_AIM` of ``forces.target_max_displacement``
    by the median linear response of the examples' fields), applied as ``forces.loading`` says,
    and its scenario draws (gravity change, indentation; ``scenario_rng(seed)``).

    Args:
        sc: the scenario.
        config: the whole configuration (material, solver, forces).
        seeds: (k,) sample seeds.

    Returns:
        ``[(title, displacement (n, 3) mm)]``, one per seed; a sample the solver could not
        finish gives its last converged state, and its title says so.
    """
    from ..errors import ConvergenceError
    from ..fem import Solver
    from .scenario import scenario_rng

    problem = sc.problem()
    solver = Solver(problem, config.solver)
    n = sc.mesh.n_vertices
    fields = [None] * len(seeds)
    if config.scenario.lbo_forces:
        alpha = example_alpha(sc, config, seeds, solver)
        fields = [sc.surface_forces.field(s, alpha)[0] for s in seeds]
    out = []
    for k, (seed, field) in enumerate(zip(seeds, fields)):
        draw = sc.draw(scenario_rng(seed))
        surface, extra = sc.solve_inputs(draw, field, config.forces.loading)
        try:
            res = solver.solve(surface, **extra)
            u, note = res.displacement, ""
        except ConvergenceError as exc:
            u = exc.result.displacement if exc.result is not None else np.zeros((n, 3))
            note = f" (stopped at {100 * exc.load_fraction:.0f} % of the load)"
        out.append((f"example {k + 1}: peak {np.linalg.norm(u, axis=1).max():.1f} mm{note}", np.asarray(u)))
    return out


def write_preview_vtu(path, sc: Scenario, draws: list[ScenarioDraw], extra_point_data: dict | None = None) -> Path:
    """Write the mesh with :func:`preview_arrays`' data (and ``extra_point_data``) as ``.vtu``."""
    from ..mesh import write_mesh

    point, cell = preview_arrays(sc, draws)
    point.update(extra_point_data or {})
    return write_mesh(path, sc.mesh, point_data=point, cell_data=cell)[0]


def render_preview(path, sc: Scenario, draws: list[ScenarioDraw], deformations: list | None = None,
                   window=(1400, 900), places: dict | None = None) -> Path:
    """Render the scenario (and optional example deformations) to a PNG.

    Args:
        path: output ``.png``.
        sc: the scenario.
        draws: example draws; their indentation patches (green, with the pushes as arrows) and
            gravity directions (thin orange arrows) are shown.
        deformations: optional list of ``(title, displacement (n, 3) mm)`` drawn as extra panels,
            coloured by displacement magnitude.
        window: image size in pixels.
        places: name -> (k,) vertex ids of the places the config's rules found (a markups
            point's or an extreme rule's vertex, :func:`~.regions.region_anchors`), drawn as
            labelled spheres; the access region is drawn as gold dots.
    """
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    pv = require("pyvista", "viz", "The scenario preview")
    pv.OFF_SCREEN = True
    mesh = sc.mesh
    deformations = deformations or []
    tri = mesh.surface_triangles
    faces = np.hstack([np.full((len(tri), 1), 3), tri]).ravel()
    size = float(np.linalg.norm(mesh.extent))
    centre = mesh.points.mean(axis=0)
    point, _ = preview_arrays(sc, draws)
    cols = 1 + len(deformations)
    p = pv.Plotter(off_screen=True, shape=(1, cols), window_size=(window[0] * cols // 2 + window[0] // 2, window[1]))
    p.subplot(0, 0)
    p.set_background("white")
    surf = pv.PolyData(mesh.points, faces)
    surf.point_data["support"] = point["support"].astype(float)
    p.add_mesh(surf, scalars="support", cmap=["tan", "lightskyblue", "crimson", "royalblue"], clim=(-0.5, 3.5),
               opacity=0.55, show_edges=True, edge_color="grey", line_width=0.3, show_scalar_bar=False)
    if len(sc.pinned):
        p.add_points(mesh.points[sc.pinned], color="royalblue", point_size=14, render_points_as_spheres=True)
    _draw_places(p, mesh, sc, places or {})
    for k, d in enumerate(draws):
        ind = d.indentation
        if ind is None:
            continue
        p.add_points(mesh.points[ind.vertices], color="green", point_size=9, render_points_as_spheres=True)
        start = mesh.points[ind.centre] - 2.0 * ind.displacement
        p.add_mesh(pv.Arrow(start=start, direction=ind.displacement, scale=2.0 * float(np.linalg.norm(ind.displacement))),
                   color="darkgreen")
        p.add_point_labels(mesh.points[[ind.centre]], [f"I{k + 1}"], font_size=12, text_color="darkgreen",
                           shape_opacity=0.5, always_visible=True, show_points=False)
    if sc.gravity is not None:
        g = sc.config.gravity
        arrow = 0.35 * size
        for vec, colour in ((g.imaging_direction, "black"), (g.surgery_direction, "darkorange")):
            v = np.asarray(vec, dtype=np.float64)
            p.add_mesh(pv.Arrow(start=centre, direction=v / np.linalg.norm(v), scale=arrow, shaft_radius=0.02), color=colour)
        for d in draws:
            arrow_mesh = pv.Arrow(start=centre, direction=d.gravity_direction, scale=0.8 * arrow, shaft_radius=0.01,
                                  tip_radius=0.04)
            p.add_mesh(arrow_mesh,
                       color="orange", opacity=0.6)
    legend = [("elastic support (springs)", "lightskyblue"), ("attached region", "crimson"),
              ("pinned vertices", "royalblue"), ("indentation examples I", "green")]
    if sc.sites is not None:
        legend.append(("surgical access", "gold"))
    if sc.gravity is not None:
        legend += [("gravity at imaging", "black"), ("gravity in surgery: nominal, examples", "darkorange")]
    p.add_legend(legend, bcolor=None, loc="upper left", size=(0.38, 0.2))
    p.add_text(f"scenario '{sc.config.name}'", font_size=10, position="upper_right")
    p.add_axes()
    for k, (title, u) in enumerate(deformations):
        p.subplot(0, k + 1)
        p.set_background("white")
        moved = pv.PolyData(mesh.points + u, faces)
        moved.point_data["displacement (mm)"] = np.linalg.norm(u, axis=1)
        p.add_mesh(moved, scalars="displacement (mm)", cmap="viridis", show_edges=False,
                   scalar_bar_args={"title": "displacement (mm)", "vertical": False, "title_font_size": 12,
                                    "label_font_size": 10})
        p.add_mesh(surf.copy(), style="wireframe", color="grey", opacity=0.12)
        p.add_text(title, font_size=9)
    p.link_views()
    p.view_vector((1.0, 0.5, 0.35), viewup=(0.0, 0.0, 1.0))
    p.screenshot(str(path))
    p.close()
    return Path(path)


def _draw_places(p, mesh, sc: Scenario, places: dict) -> None:
    """The access region (gold dots) and the places rules found (magenta spheres with their names)."""
    if sc.sites is not None and len(sc.sites.access) < len(mesh.surface_vertices):
        p.add_points(mesh.points[sc.sites.access], color="gold", point_size=6, render_points_as_spheres=True)
    for name, ids in places.items():
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size:
            p.add_point_labels(mesh.points[ids], [name] * len(ids), font_size=11, text_color="darkmagenta",
                               point_color="magenta", point_size=16, render_points_as_spheres=True,
                               shape_opacity=0.5, always_visible=True)
