"""Coverage report: areas, density and gaps per link."""
import numpy as np

from skinsafe.core.design.coverage import coverage_report
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5


def test_coverage_numbers_and_gaps_grow_when_taxels_are_removed():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    full = coverage_report(design, robot.model)["forearm_link"]
    # 750 taxels at 1 cm pitch (25 around x 30 rows): 750 cm^2 of skin; the forearm capsule r=4 cm, 34 cm tube
    assert full["taxels"] == 750 and np.isclose(full["skinned_area_m2"], 0.075, rtol=0.015)
    tube = 2 * np.pi * 0.04 * 0.34 + 4 * np.pi * 0.04 ** 2
    assert np.isclose(full["link_area_m2"], tube, rtol=2e-3)  # the tessellation is within 0.05 mm
    assert np.isclose(full["density_per_cm2"], 1.0, rtol=0.015)
    # the tube is wrapped but for the ends under the elbow and wrist housings (the caps are bare too):
    # bare share about the caps' and those 3-4 cm of tube's share of the area
    caps = 4 * np.pi * 0.04 ** 2 / tube
    ends = 2 * np.pi * 0.04 * np.array([0.03, 0.045]) / tube
    assert 0.8 * (caps + ends[0]) < full["bare_fraction"] < 1.2 * (caps + ends[1])
    # drop the taxels on one side of the tube: a bare strip opens
    fi = design.bodies.index("forearm_link")
    keep = ~((design.taxels.body == fi) & (design.taxels.positions[:, 1] > 0.0))
    half = coverage_report(design.with_taxels(design.taxels.subset(keep)), robot.model)["forearm_link"]
    assert half["bare_fraction"] > full["bare_fraction"] + 0.3
    assert half["largest_gap_mm"] > full["largest_gap_mm"]


def test_link_area_is_the_visual_surface_counted_once(tmp_path):
    """A link with a visual mesh and a (larger) collision box: its area is the visual mesh's alone."""
    import trimesh

    from skinsafe.core.design.coverage import body_area
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.skin.model import RobotRef

    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(tmp_path / "ball.stl")
    (tmp_path / "r.urdf").write_text(
        '<robot name="r"><link name="base"/><link name="arm"><visual><geometry><mesh filename="ball.stl"/>'
        '</geometry></visual><collision><geometry><box size="0.2 0.2 0.2"/></geometry></collision></link>'
        '<joint name="j" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    robot = load_robot(RobotRef("urdf", "r", str(tmp_path / "r.urdf")))
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05).area
    assert np.isclose(body_area(robot.model, "arm"), sphere, rtol=1e-6)


def test_uncovered_points_are_off_every_module_and_a_covered_link_has_none():
    from scipy.spatial import cKDTree

    from skinsafe.core.design.coverage import reach, uncovered_points
    from skinsafe.core.design.surface import cached_surfaces

    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    fi = design.bodies.index("forearm_link")
    on = design.taxels.body == fi
    assert np.isclose(reach(design, fi), 0.01)  # the modules' 1 cm pitch
    full = uncovered_points(design, robot.model, fi)
    surface = cached_surfaces(robot.model, ["forearm_link"])["forearm_link"].vertices
    # the bare caps and tube ends (densely tessellated): some, not all, of the surface's vertices; each point
    # > 1 cm from every taxel of the link
    assert 0 < len(full) < len(surface)
    assert cKDTree(design.taxels.positions[on]).query(full)[0].min() > 0.01
    assert np.isin(full.view([("", full.dtype)] * 3), surface.view([("", surface.dtype)] * 3)).all()
    # drop the taxels on one side: the bare strip's points join, all on that side (y > 0, beyond 1 cm)
    keep = ~(on & (design.taxels.positions[:, 1] > 0.0))
    half = uncovered_points(design.with_taxels(design.taxels.subset(keep)), robot.model, fi)
    extra = half[~np.isin(half.view([("", half.dtype)] * 3), full.view([("", full.dtype)] * 3)).ravel()]
    assert len(extra) > 100 and extra[:, 1].min() > 0.0
    # a taxel on every surface vertex (same modules, same reach): the link is covered, nothing bare on it
    idx = np.flatnonzero(on)[np.arange(len(surface)) % on.sum()]
    cover = design.taxels.subset(idx)
    cover.positions[:] = surface
    covered = design.with_taxels(cover)
    assert reach(covered, fi) == reach(design, fi) and len(uncovered_points(covered, robot.model, fi)) == 0
    # a link without taxels: all of it is bare
    ui = design.bodies.index("upper_arm_link")
    bare = design.with_taxels(design.taxels.subset(design.taxels.body != ui))
    assert len(uncovered_points(bare, robot.model, ui)) == len(cached_surfaces(robot.model, ["upper_arm_link"])["upper_arm_link"].vertices)


def test_covered_area_counts_overlapping_and_crowded_cells_once():
    """The covered area is the cells' union on the link: a module laid twice over itself covers what
    it covered, and the same taxels crowded to half the pitch cover a quarter of it."""
    from dataclasses import replace

    from skinsafe.core.design.coverage import covered_area
    from skinsafe.core.skin.ids import stable_ids
    from skinsafe.core.skin.model import Taxels

    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    fi = design.bodies.index("forearm_link")
    t = design.taxels
    one = int(t.module[t.body == fi][0])
    m = next(m for m in design.modules if m.id == one)
    mine = t.subset(t.module == one)
    alone = design.with_taxels(mine)
    area = covered_area(alone, robot.model, fi)
    assert np.isclose(area, len(mine) * m.pitch ** 2, rtol=0.03)
    twice = Taxels.concatenate([mine, replace(mine.subset(np.arange(len(mine))), module=mine.module + 1000)])
    twice = replace(twice, ids=stable_ids(twice.module))
    assert np.isclose(covered_area(design.with_taxels(twice), robot.model, fi), area, rtol=1e-9)
    centre = mine.positions.mean(axis=0)
    crowded = replace(mine.subset(np.arange(len(mine))), positions=centre + 0.5 * (mine.positions - centre))
    crowded_area = covered_area(design.with_taxels(crowded), robot.model, fi)
    assert crowded_area < 0.45 * area  # a quarter of the cells' area plus their borders, never the count x pitch^2
