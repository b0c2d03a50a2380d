"""``tissuecast scenario preview CONFIG``: show a config's clinical scenario before simulating it.

Writes ``PREFIX.vtu`` (the mesh with the support codes 0 free, 1 elastic support, 2 attached,
3 pinned, the spring stiffness, example indentation patches and pushes, the first example's
gravity change, and the material regions as cell data; open it in ParaView or 3D Slicer in the
mesh's coordinates, mm), ``PREFIX.json`` (the scenario and the example draws: those of the data
set's first samples) and, unless ``--no-png``, ``PREFIX.png``. Vertex ids are 0-based.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluate import json_output


def register(sub) -> None:
    p = sub.add_parser("scenario", help="show the clinical scenario of a config (supports, loads, materials)")
    ssub = p.add_subparsers(dest="scenario_command", metavar="ACTION", required=True)
    pv = ssub.add_parser("preview", help="PNG + VTU + JSON of the supports, regions, gravity and indentation sites",
                         description=__doc__.split("\n\n")[1] if __doc__ else None)
    pv.add_argument("config", help="TOML config file or a packaged preset (embedded, paper, quick)")
    pv.add_argument("--out", default="scenario", metavar="PREFIX", help="output prefix (default 'scenario')")
    pv.add_argument("--examples", type=int, default=3, metavar="N",
                    help="example draws shown: those of the data set's first N samples (default 3)")
    pv.add_argument("--no-png", action="store_true", help="skip the picture (needs pyvista, extra 'viz')")
    pv.add_argument("--no-deformations", dest="deformations", action="store_false",
                    help="skip solving the examples (by default each is solved with the built-in solver and drawn "
                    "deformed, coloured by |u|, next to the supports; VTU point data displacement_example_K, mm)")
    pv.set_defaults(func=run_preview)


def run_preview(args) -> int:
    from ..dataset.sample_plan import sample_seed
    from ..scenario import scenario_from_config, scenario_rng
    from ..scenario.preview import example_deformations, render_preview, scenario_places, write_preview_vtu
    from ..app.configuration import load_run_config

    cfg = load_run_config(args.config)
    mesh, markers, fixed, sc = scenario_from_config(cfg)
    seeds = [sample_seed(cfg.dataset.seed, i) for i in range(max(0, args.examples))]
    draws = [sc.draw(scenario_rng(s)) for s in seeds]
    prefix = Path(args.out)
    if prefix.parent != Path("."):
        prefix.parent.mkdir(parents=True, exist_ok=True)
    summary = sc.summary()
    places = scenario_places(sc)
    doc = {"ids_are_0_based": True, "units": {"length": "mm", "force": "N", "density": "t/mm^3"},
           "scenario": summary, "markers": markers.tolist(), "pinned": sc.pinned.tolist(),
           "attached": sc.attached.tolist(),
           "places": {name: {"vertices": ids.tolist(), "lps_mm": mesh.points[ids].tolist()} for name, ids in places.items()},
           "access": [] if sc.sites is None else sc.sites.access.tolist(),
           "examples": [{"sample": i, **d.record(), "indent_vertices": [] if d.indentation is None
                         else d.indentation.vertices.tolist()} for i, d in enumerate(draws)]}
    deformations, shares, alpha = [], {}, 0.0
    if args.deformations:
        from ..fem.linear import one_blas_thread
        from ..scenario.load_shares import load_shares
        from ..scenario.preview import LINEAR_AIM, example_alpha

        with one_blas_thread():  # as the data set's workers solve: faster, same bits everywhere
            deformations = example_deformations(sc, cfg, seeds)
            alpha = example_alpha(sc, cfg, seeds) if cfg.scenario.lbo_forces else 0.0
            shares = load_shares(sc, cfg, seeds, alpha) if len(seeds) else {}
    doc["load_shares"] = shares
    doc["example_peak_displacement_mm"] = [float(np.linalg.norm(u, axis=1).max()) for _, u in deformations]
    extra = {f"displacement_example_{k + 1}": u for k, (_, u) in enumerate(deformations)}
    written = [write_preview_vtu(prefix.with_name(prefix.name + ".vtu"), sc, draws, extra)]
    path = prefix.with_name(prefix.name + ".json")
    path.write_text(json_output.dumps(doc, indent=2, default=float) + "\n", encoding="utf-8")
    written.append(path)
    if not args.no_png:
        written.append(render_preview(prefix.with_name(prefix.name + ".png"), sc, draws, deformations, places=places))
    print(f"scenario '{summary['name']}' on {mesh.n_vertices} vertices ({cfg.mesh.path or 'built-in phantom'}); "
          "ids 0-based")
    print(f"  pinned vertices   {len(sc.pinned)}")
    print(f"  attached region   {len(sc.attached)} surface vertices (rule {cfg.scenario.attached.rule})"
          + _place_text(mesh, places.get("attached")))
    if sc.sites is not None:
        print(f"  surgical access   {len(sc.sites.access)} surface vertices (rule {cfg.scenario.indentation.access.rule})"
              + _place_text(mesh, places.get("access")) + f", {len(sc.sites.centres)} eligible patch centres")
    if sc.springs is not None:
        s = cfg.scenario.springs
        print(f"  elastic support   {len(sc.spring_region)} surface vertices, {len(sc.springs)} nodal springs, "
              f"k_n {s.normal_stiffness:g} / k_t {s.tangential_stiffness:g} N/mm^3 (surroundings of E = "
              f"{cfg.material.youngs_modulus:g} MPa over {cfg.material.youngs_modulus / s.normal_stiffness:.3g} mm)")
    print(f"  LBO forces        {'on' if cfg.scenario.lbo_forces else 'off'}")
    for i, d in enumerate(draws):
        parts = []
        if d.gravity_direction is not None:
            cosine = np.clip(d.gravity_direction @ _unit(cfg.scenario.gravity.imaging_direction), -1, 1)
            parts.append(f"gravity {np.round(d.gravity_direction, 3).tolist()} "
                         f"({np.degrees(np.arccos(cosine)):.1f} deg from imaging)")
        if d.indentation is not None:
            ind = d.indentation
            parts.append(f"indentation at vertex {ind.centre} ({len(ind.vertices)} vertices), depth {ind.depth:.2f} mm, "
                         f"slide {ind.slide:.2f} mm")
        print(f"  sample {i}: {'; '.join(parts) or 'LBO forces only'}")
    if sc.materials is not None:
        for name, v in sc.materials.draws.items():
            print(f"  material {name}: E {v['youngs_modulus']:.4g} MPa, nu {v['poisson_ratio']:.4g}")
    if shares:
        from ..scenario.load_shares import format_load_shares

        how = ("dataset.alpha" if cfg.dataset.alpha > 0 else
               f"a linear guess aiming at {100 * LINEAR_AIM:g} % of forces.target_max_displacement, not the data set's "
               "calibration, which sets it from nonlinear pilots: `tissuecast dataset info STORE --load-shares N` gives "
               "the data set's own shares")
        print(f"  each load alone (the examples, nominal parameters; the surface field at {alpha:.4g} N, {how}):")
        for line in format_load_shares(shares):
            print(f"    {line}")
    for p in written:
        print(f"wrote {p}")
    return 0


def _place_text(mesh, ids) -> str:
    """``" at vertex 12 (LPS 1.0, 2.0, 3.0 mm)"`` for the places a rule found; empty without."""
    if ids is None or not len(ids):
        return ""
    return " at " + "; ".join(f"vertex {int(i)} (LPS {', '.join(f'{x:.1f}' for x in mesh.points[i])} mm)" for i in ids[:4])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)
