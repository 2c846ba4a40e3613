"""The built-in sample skins pass `skinsafe check`'s audit: no taxel under a joint housing of its
own link or buried under the next link's at every pose, no outline overhanging."""
import warnings

import pytest

from skinsafe.core.design.audit import audit, buried_taxels
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_panda, build_ur5
from skinsafe.core.sim.scene import build_scene


@pytest.mark.parametrize("name,builder,taxels", [("ur5", build_ur5, 2149), ("panda", build_panda, 1330)])
def test_sample_skin_passes_the_audit_and_scenes_do_not_warn(name, builder, taxels):
    robot = builder()
    design = make_sample_design(name, robot=robot)
    assert design.n_taxels == taxels
    assert audit(design, robot.model, robot.home, poses=8) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_scene(design, robot)  # every taxel within 1 mm of the contact surface


def test_the_old_end_to_end_wrap_is_refused():
    """Without the housing check (the whole capsule wrapped) the UR5 skin has buried taxels."""
    from skinsafe.core.design import sample

    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    full = sample.wrap_cylinder(robot.model, int(robot.model.body("forearm_link").geomadr[0]), 0.01, 8, 8, 0.005,
                                0, design.bodies.index("forearm_link"), "forearm_link", 0.006, 2.0)[1]
    assert len(full) > (design.taxels.body == design.bodies.index("forearm_link")).sum() == 750
    assert buried_taxels(design.with_taxels(full), robot.model, robot.home, poses=8).sum() > 0
