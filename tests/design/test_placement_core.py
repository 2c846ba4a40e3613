"""Placement core (pure numpy, no Blender): surfaces, conformal wrapping, frames, refusals, boards."""
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from skinsafe.core.design.placement import (
    PlacementError,
    build_design,
    place_module,
    points_in_polygon,
    replace_module,
    template_grid,
)
from skinsafe.core.design.surface import Surface, body_surface
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin.model import DesignError, Module, RobotRef

E = 0.13585 - 0.1197  # forearm capsule axis: y = 0, z = E, x from -0.02 to -0.36, radius 0.04


@pytest.fixture(scope="module")
def ur5():
    return build_ur5()


@pytest.fixture(scope="module")
def forearm(ur5):
    return body_surface(ur5.model, "forearm_link")


def _module(mid=0, **kw):
    base = dict(id=mid, name=f"m{mid}", body="forearm_link", rows=16, cols=16, pitch=0.005, taxel_diameter=0.003,
                margin=0.001, min_bend_radius=0.01)
    return Module(**{**base, **kw})


def test_closest_points_match_brute_force():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(60, 3))
    t = rng.integers(0, 60, size=(80, 3))
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    s = Surface.from_mesh(v, t)
    p = rng.normal(size=(200, 3)) * 1.5
    q, _, tri, d = s.closest(p)
    # brute force over all triangles (big overlapping random triangles: the hierarchy's boxes overlap
    # everywhere), each point on each triangle by trimesh's own closest-point routine
    every = np.repeat(s.vertices[s.triangles][None], len(p), 0).reshape(-1, 3, 3)
    ref = trimesh.triangles.closest_point(every, np.repeat(p, len(s.triangles), 0)).reshape(len(p), -1, 3)
    d_ref = np.linalg.norm(ref - p[:, None], axis=2).min(axis=1)
    assert np.allclose(d, d_ref, atol=1e-12)
    assert np.allclose(np.linalg.norm(q - p, axis=1), d)
    # the answer lies on the triangle it names
    on = trimesh.triangles.closest_point(s.vertices[s.triangles[tri]], q)
    assert np.abs(on - q).max() < 1e-12


def test_capsule_surface_close_to_the_true_shape(forearm):
    rng = np.random.default_rng(1)
    n = 500
    x, ang, rad = rng.uniform(-0.3, -0.05, n), rng.uniform(0, 2 * np.pi, n), rng.uniform(0.02, 0.08, n)
    p = np.stack([x, rad * np.cos(ang), E + rad * np.sin(ang)], 1)
    q, nrm, _, d = forearm.closest(p)
    assert np.abs(np.hypot(q[:, 1], q[:, 2] - E) - 0.04).max() < 1e-4
    radial = np.stack([0 * x, np.cos(ang), np.sin(ang)], 1)
    assert np.degrees(np.arccos(np.clip(np.sum(nrm * radial, 1), -1, 1))).max() < 2.0
    assert np.abs(d - np.abs(rad - 0.04)).max() < 1e-4


def test_geodesic_wrap_keeps_pitch_on_the_surface_and_frames_right(forearm):
    pm = place_module(forearm, _module(), [-0.2, 0.0, E + 0.05], [-1, 0, 0])
    assert len(pm) == 256
    p = pm.positions
    assert np.abs(np.hypot(p[:, 1], p[:, 2] - E) - 0.04).max() < 5e-4  # on the surface within 0.5 mm
    P = p.reshape(16, 16, 3)
    arc = np.diff(np.unwrap(np.arctan2(P[..., 1], P[..., 2] - E), axis=0), axis=0) * 0.04  # across rows: around
    assert np.allclose(np.abs(arc), 0.005, rtol=0.01)
    assert np.allclose(np.abs(np.diff(P[..., 0], axis=1)), 0.005, rtol=1e-6)  # along rows: the axis
    F = pm.frames
    assert np.abs(np.einsum("nji,njk->nik", F, F) - np.eye(3)).max() < 1e-9
    assert np.allclose(np.linalg.det(F), 1.0)
    radial = np.stack([0 * p[:, 0], p[:, 1], p[:, 2] - E], 1)
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.sum(F[:, :, 2] * radial, 1).min() > np.cos(np.radians(1))  # z = outward normal
    assert np.allclose(F[:, :, 0], [-1, 0, 0], atol=1e-6)  # x along the rows (the given direction)
    assert np.allclose(pm.min_bend_radius, 0.04, rtol=0.02)
    assert pm.strain < 5e-3  # a cylinder is developable: the wrap is an isometry (to the 0.05 mm facets)
    # projection keeps the flat pitch in the tangent plane, so arc spacing shrinks toward the sides: a flat
    # circuit cannot do that, and the placement is refused naming the pair, the strain and what fits
    with pytest.raises(PlacementError, match=r"in-plane strain -\d\d\.\d% between taxels row \d+ col \d+ and row "
                       r"\d+ col \d+ on 'forearm_link' .* over the FPC's 1\.0% .*: a 2x16 module fits here") as e:
        place_module(forearm, _module(), [-0.2, 0.0, E + 0.05], [-1, 0, 0], method="projection")
    assert e.value.kind == "strain"
    pj = place_module(forearm, replace(_module(), rows=2), [-0.2, 0.0, E + 0.05], [-1, 0, 0], method="projection")
    assert pj.strain <= 0.01


def test_refusals_name_what_and_where(forearm, ur5):
    with pytest.raises(PlacementError, match=r"bend radius 39\.\d mm .* below the FPC's minimum 50\.0 mm") as e:
        place_module(forearm, _module(min_bend_radius=0.05), [-0.2, 0, E + 0.05], [-1, 0, 0])
    assert e.value.kind == "bend_radius" and len(e.value.where[2]) == 3
    wrist3 = body_surface(ur5.model, "wrist_3_link")
    with pytest.raises(PlacementError, match="falls off the surface of 'wrist_3_link'") as e:
        place_module(wrist3, _module(body="wrist_3_link", rows=4), [0.04, 0, 0.03], [0, 0, 1])
    assert e.value.kind == "off_surface"
    first = place_module(forearm, _module(), [-0.2, 0, E + 0.05], [-1, 0, 0])
    with pytest.raises(PlacementError, match="overlaps module 0 'm0'") as e:
        place_module(forearm, _module(1), [-0.23, 0.0, E + 0.05], [-1, 0, 0], others=[first])
    assert e.value.kind == "overlap"
    # side by side along the axis with room for both margins: accepted
    place_module(forearm, _module(1), [-0.2 - 16 * 0.005 - 0.001, 0, E + 0.05], [-1, 0, 0], others=[first])
    with pytest.raises(PlacementError, match="a strip has one row"):
        template_grid(_module(template="strip", rows=2))


def test_curve_template_keeps_cells_inside_the_outline():
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    circle = 0.0201 * np.stack([np.cos(ang), np.sin(ang)], 1)
    uv, row, col = template_grid(_module(template="curve", rows=8, cols=8, pitch=0.01), circle)
    assert len(uv) == 12  # cells at (+-5, +-5) and (+-15, +-5) and (+-5, +-15) mm lie within 20.1 mm
    assert np.hypot(uv[:, 0], uv[:, 1]).max() < 0.0201
    assert points_in_polygon(np.array([[0.0, 0.0], [1.0, 1.0]]), circle).tolist() == [True, False]


def test_design_boards_and_regeneration(forearm):
    mods = [place_module(forearm, _module(i, rows=8, cols=8), [-0.06 - 0.05 * i, 0, E + 0.05], [-1, 0, 0])
            for i in range(3)]
    d = build_design(RobotRef(), mods, capacity=128)
    assert d.n_taxels == 192 and len(d.boards) == 2
    for m in d.modules:  # a module stays on one board
        assert set(d.taxels.board[d.taxels.module == m.id].tolist()) == {m.board}
    with pytest.raises(DesignError, match="exceed a board's 32 channels"):
        build_design(RobotRef(), mods, capacity=32)
    moved = place_module(forearm, _module(1, rows=8, cols=8), [-0.11, 0.0, E - 0.05], [-1, 0, 0], others=[mods[0]])
    d2 = replace_module(d, moved)
    on = d2.taxels.module == 1
    assert np.array_equal(d2.taxels.positions[on], moved.positions)
    assert np.array_equal(d2.taxels.positions[~on], d.taxels.positions[~on])
    assert (d2.taxels.positions[on, 2] < E).all()
