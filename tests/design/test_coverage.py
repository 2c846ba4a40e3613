"""Coverage report: areas, density and gaps per link."""
import numpy as np

from skinsafe.core.design.coverage import coverage_report
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5


def test_coverage_numbers_and_gaps_grow_when_taxels_are_removed():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    full = coverage_report(design, robot.model)["forearm_link"]
    # 825 taxels at 1 cm pitch: 825 cm^2 of skin; the forearm capsule r=4 cm, 34 cm tube
    assert full["taxels"] == 825 and np.isclose(full["skinned_area_m2"], 0.0825)
    tube = 2 * np.pi * 0.04 * 0.34 + 4 * np.pi * 0.04 ** 2
    assert np.isclose(full["link_area_m2"], tube)
    assert np.isclose(full["density_per_cm2"], 1.0)
    # the tube is wrapped end to end (the caps are bare): bare share about the caps' share of the area
    caps = 4 * np.pi * 0.04 ** 2 / tube
    assert 0.5 * caps < full["bare_fraction"] < 1.5 * caps
    # drop the taxels on one side of the tube: a bare strip opens
    fi = design.bodies.index("forearm_link")
    keep = ~((design.taxels.body == fi) & (design.taxels.positions[:, 1] > 0.0))
    half = coverage_report(design.with_taxels(design.taxels.subset(keep)), robot.model)["forearm_link"]
    assert half["bare_fraction"] > full["bare_fraction"] + 0.3
    assert half["largest_gap_mm"] > full["largest_gap_mm"]
