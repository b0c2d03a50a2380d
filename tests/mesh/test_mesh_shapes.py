"""Test anatomies (tissuecast.mesh.shapes): sizes, volumes, interior vertices, element quality."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecast.errors import MarkerError
from tissuecast.markers import select_fixed_vertices
from tissuecast.mesh.shapes import DOME_EXTENT, bent_tube, dome_surface, slender_rod


@pytest.mark.parametrize("layers", [1, 2])
def test_bent_tube_has_a_thin_wall_and_its_volume(layers):
    radius, wall, length = 4.0, 0.8, 60.0
    tube = bent_tube(radius=radius, wall=wall, wall_layers=layers, length=length, around=24, along=40)
    n_rings = 41 * 24
    assert tube.n_points == n_rings * (layers + 1) and tube.n_tets == 6 * 40 * 24 * layers
    # the wall: one layer leaves no interior vertex, two leave only the middle ring
    assert len(tube.interior_vertices) == (0 if layers == 1 else (41 - 2) * 24)
    # volume of a bent annulus: pi (R^2 - r^2) L (Pappus), less the chords of 24 facets, +- the jitter
    exact = np.pi * (radius**2 - (radius - wall) ** 2) * length
    assert tube.volume == pytest.approx(exact, rel=0.03)
    q = tube.quality
    assert q.radius_ratio_min < 0.15  # some flat (sliver) elements, as real vessel meshes have
    assert q.radius_ratio_mean > 0.3
    # a 90-degree bend: the extent in x and z is about the bend radius plus the tube
    bend_radius = length / (np.pi / 2)
    np.testing.assert_allclose(tube.extent[[0, 2]], bend_radius + radius, rtol=0.05)
    assert tube.extent[1] == pytest.approx(2 * radius, rel=0.05)


def test_bent_tube_is_the_same_on_every_call_and_refuses_bad_sizes():
    a, b = bent_tube(seed=3), bent_tube(seed=3)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.tets, b.tets)
    with pytest.raises(ValueError, match="0 < wall < radius"):
        bent_tube(radius=1.0, wall=1.5)


def test_slender_rod_is_long_thin_and_structured():
    rod = slender_rod(length=120.0, width=8.0, cells_along=60, cells_across=2, bend=10.0)
    assert rod.n_points == 61 * 9 and rod.n_tets == 6 * 60 * 4
    assert rod.volume == pytest.approx(120.0 * 64.0, rel=1e-9)  # a sheared bar keeps its volume
    assert len(rod.interior_vertices) == 59  # one line of interior vertices along the bar
    assert rod.extent[2] == pytest.approx(120.0) and rod.extent[0] == pytest.approx(18.0)


def test_dome_surface_has_its_extent():
    points, triangles = dome_surface(3)
    np.testing.assert_allclose(points.max(axis=0) - points.min(axis=0), DOME_EXTENT, rtol=1e-12)
    v = points[triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    ellipsoid = np.pi / 6 * np.prod(DOME_EXTENT)  # the ellipsoid inscribed in the same box
    assert 0.6 * ellipsoid < volume < ellipsoid  # outward, and less than it (the flattened base)


def test_wall_one_element_thick_names_the_supports_to_use():
    tube = bent_tube(wall_layers=1)
    with pytest.raises(MarkerError, match=r"no interior vertices.*\[scenario.attached\] or \[scenario.springs\]"):
        select_fixed_vertices(tube, 3)
    two = bent_tube(wall_layers=2)
    pins = select_fixed_vertices(two, 3)  # two layers: the compact rule finds pins in the wall's middle
    assert set(pins.tolist()) <= set(two.interior_vertices.tolist())


def test_wall_one_element_thick_is_held_by_its_ends_without_pins(tmp_path):
    """scenario.pins = false: no pins are chosen, so a mesh without interior vertices is held by
    an attached region and springs instead of stopping at the pin rule."""
    from tissuecast.config import Config, with_overrides
    from tissuecast.mesh import write_mesh
    from tissuecast.scenario import scenario_from_config

    tube = bent_tube(wall_layers=1, around=12, along=10)
    write_mesh(tmp_path / "tube.vtu", tube)
    section = 12 * 2  # the shape numbers its vertices section by section: 12 around x 2 through the wall
    ends = np.r_[np.arange(section), np.arange(tube.n_vertices - section, tube.n_vertices)]
    over = {"mesh": {"path": str(tmp_path / "tube.vtu")}}
    held = {"pins": False, "attached": {"rule": "ids", "ids": ends.tolist()}, "springs": {"rule": "surface"}}
    mesh, markers, pins, scenario = scenario_from_config(with_overrides(Config(), scenario=held, **over))
    assert len(pins) == 0 and len(markers) == 5
    assert np.array_equal(np.sort(scenario.supported), ends)
    with pytest.raises(MarkerError, match="no interior vertices"):
        scenario_from_config(with_overrides(Config(), scenario={**held, "pins": True}, **over))
