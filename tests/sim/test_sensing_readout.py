"""Skin readout: probes poke taxels on exported UR5 and Panda scenes; footprint, forces, touch reference."""
import mujoco
import numpy as np
import pytest

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_panda, build_ur5
from skinsafe.core.sim.readout import SkinReadout, TouchReadout
from skinsafe.core.sim.scene import Obstacle, SceneOptions
from skinsafe.exporters.mjcf import export_scene

PROBE_R = 0.006


@pytest.fixture(scope="module", params=["ur5", "panda"])
def scene(request, tmp_path_factory):
    design = make_sample_design(request.param, pitch=0.01)
    robot = build_ur5() if request.param == "ur5" else build_panda()
    path = export_scene(design, robot, tmp_path_factory.mktemp(request.param) / "scene",
                        [Obstacle("probe", "sphere", (PROBE_R,), pos=(0, 0, -5), mocap=True)],
                        SceneOptions(touch_sensors=True))
    model = mujoco.MjModel.from_xml_path(str(path))
    pos, frames = TaxelKinematics(model, design).poses(robot.home)
    return design, robot, model, pos.copy(), frames.copy()


def _poke(model, robot, at, normal, depth=0.0005):
    """Forward dynamics with the probe pressed `depth` into the surface at `at`; the probe's contacts."""
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    data.ctrl[:] = robot.home
    data.mocap_pos[0] = at + normal * (PROBE_R - depth)
    mujoco.mj_forward(model, data)
    probe = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "probe")
    mine = [c for c in range(data.ncon) if probe in data.contact.geom[c]]
    f = np.zeros(6)
    forces = []
    for c in mine:
        mujoco.mj_contactForce(model, data, c, f)
        forces.append(f[0])
    return data, mine, float(sum(forces))


def _pokeable(design, model, robot, pos, frames, count=12):
    """Taxels where the probe meets exactly one geom, of the taxel's own body, and pushes."""
    out = []
    for i in np.random.default_rng(1).permutation(design.n_taxels):
        data, mine, total = _poke(model, robot, pos[i], frames[i][:, 2])
        if len(mine) == 1 and total > 1e-3:
            other = [g for g in data.contact.geom[mine[0]] if model.geom(g).name != "probe"][0]
            if model.body(model.geom_bodyid[other]).name == design.body_of(i):
                out.append(i)
        if len(out) == count:
            break
    return out


def test_poke_lights_that_taxel_and_sum_matches_contact_force(scene):
    design, robot, model, pos, frames = scene
    readout, touch = SkinReadout(model, design), TouchReadout(model, design)
    taxels = _pokeable(design, model, robot, pos, frames)
    assert len(taxels) >= 8
    for i in taxels:
        data, _, total = _poke(model, robot, pos[i], frames[i][:, 2])
        f = readout.read(data)
        assert f.argmax() == i
        lit = np.flatnonzero(f > 0)
        assert np.linalg.norm(pos[lit] - pos[i], axis=1).max() <= 0.0101  # the taxel and at most neighbours
        assert f.sum() == pytest.approx(total, rel=0.05)
        t = touch.read(data)
        assert np.flatnonzero(t > 0).tolist() == [i] and t[i] == pytest.approx(total, rel=0.05)


def test_off_centre_poke_is_shared_by_neighbours_and_nearest_matches_touch(scene):
    design, robot, model, pos, frames = scene
    lin, near, touch = SkinReadout(model, design), SkinReadout(model, design, kernel="nearest"), \
        TouchReadout(model, design)
    i = _pokeable(design, model, robot, pos, frames, count=1)[0]
    x = frames[i][:, 0]
    if np.linalg.norm(pos - (pos[i] + 0.01 * x), axis=1).min() > 1e-3:  # the last column before the seam's gap
        x = -x
    data, _, total = _poke(model, robot, pos[i] + 0.3 * 0.01 * x, frames[i][:, 2])
    f = lin.read(data)
    assert f.sum() == pytest.approx(total, rel=0.05)
    assert f[i] > 0.5 * total and 0 < f[i] < total  # 70 % of the way to its neighbour: shared
    n = near.read(data)
    np.testing.assert_allclose(n, touch.read(data), rtol=1e-6, atol=1e-9)


def test_no_contact_reads_zero_and_disabled_taxels_stay_zero(scene):
    design, robot, model, pos, frames = scene
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    mujoco.mj_forward(model, data)
    assert not SkinReadout(model, design).read(data).any()
    i = _pokeable(design, model, robot, pos, frames, count=1)[0]
    off = design.with_taxels(design.taxels.subset(np.arange(design.n_taxels)))
    off.taxels.enabled[i] = False
    r = SkinReadout(model, off)
    data, _, total = _poke(model, robot, pos[i], frames[i][:, 2])
    f = r.read(data)
    assert f[i] == 0 and (f.sum() == 0 or f.sum() == pytest.approx(total, rel=0.05))


@pytest.mark.parametrize("cone", ["pyramidal", "elliptic"])
def test_contact_forces_match_mujoco(cone):
    design = make_sample_design("ur5", pitch=0.02)
    robot = build_ur5()
    from skinsafe.core.sim.scene import build_scene

    spec = build_scene(design, robot, [Obstacle("ball", "sphere", (0.03,), pos=(-0.2, 0.0, 0.6), free=True)],
                       SceneOptions(taxel_sites=False))
    if cone == "elliptic":
        spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:6] = robot.home
    data.ctrl[:] = robot.home
    r = SkinReadout(model, design)
    seen = 0
    for _ in range(400):
        mujoco.mj_step(model, data)
        if data.ncon:
            ref = np.array([_normal(model, data, c) for c in range(data.ncon)])
            np.testing.assert_allclose(r.contact_forces(data), ref, rtol=1e-9, atol=1e-9)
            seen += int((ref > 0).sum())
    assert seen > 0


def _normal(model, data, c):
    f = np.zeros(6)
    mujoco.mj_contactForce(model, data, c, f)
    return f[0]


def test_missing_touch_sensors_named():
    design = make_sample_design("ur5", pitch=0.02)
    from skinsafe.core.sim.scene import build_scene
    from skinsafe.core.skin.model import DesignError

    model = build_scene(design, build_ur5()).compile()
    with pytest.raises(DesignError, match=f"touch_{int(design.taxels.ids[0])}.*touch_sensors=True"):
        TouchReadout(model, design)


@pytest.mark.parametrize("kernel", ["linear", "nearest"])
def test_update_in_place_equals_a_fresh_read_every_step(scene, kernel):
    """`update` clears only what it lit the step before: over pokes of different taxels, off-centre
    pokes and steps with no contact, its buffer equals the reading of a readout that never read before."""
    design, robot, model, pos, frames = scene
    live = SkinReadout(model, design, kernel=kernel)
    taxels = _pokeable(design, model, robot, pos, frames, count=6)
    rng = np.random.default_rng(3)
    lit_steps = 0
    for i in taxels + taxels[::-1]:
        shift = rng.uniform(-0.4, 0.4, 2) * 0.01
        at = pos[i] + shift[0] * frames[i][:, 0] + shift[1] * frames[i][:, 1]
        for data in (_poke(model, robot, at, frames[i][:, 2])[0], _poke(model, robot, at + 0.05 * frames[i][:, 2],
                                                                          frames[i][:, 2])[0]):
            got = live.update(data)
            assert got is live.forces
            ref = SkinReadout(model, design, kernel=kernel).read(data)
            np.testing.assert_array_equal(got, ref)
            lit_steps += int(ref.any())
    assert lit_steps == len(taxels) * 2  # every poke lit something, every lift cleared it


def test_mixed_contact_dimensions_sum_each_contacts_own_rows():
    """Pyramidal cones with contacts of different dimension (1 and 3: 1 and 4 efc rows): each
    contact's normal force is the sum of its own rows, equal to MuJoCo's (mj_contactForce)."""
    from skinsafe.core.sim.scene import build_scene

    design = make_sample_design("ur5", pitch=0.02)
    robot = build_ur5()
    balls = [Obstacle("b1", "sphere", (0.03,), pos=(-0.2, 0.0, 0.6), free=True),
             Obstacle("b3", "sphere", (0.03,), pos=(-0.45, 0.0, 0.6), free=True)]
    spec = build_scene(design, robot, balls, SceneOptions(taxel_sites=False))
    for g in spec.geoms:
        g.condim = 3 if g.name == "b3" else 1
    model = spec.compile()
    assert model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    data = mujoco.MjData(model)
    data.qpos[:6] = robot.home
    data.ctrl[:] = robot.home
    r = SkinReadout(model, design)
    assert r.n_rows == -1  # rows per contact differ
    dims, checked = set(), 0
    for _ in range(600):
        mujoco.mj_step(model, data)
        f = r.update(data)
        on_skin = [c for c in range(data.ncon) if data.contact.efc_address[c] >= 0
                   and any(model.geom_bodyid[g] in r.body_ids for g in data.contact.geom[c])]
        if on_skin and r.last_missed == 0:
            dims |= {int(data.contact.dim[c]) for c in on_skin}
            assert f.sum() == pytest.approx(sum(_normal(model, data, c) for c in on_skin), rel=1e-9, abs=1e-12)
            checked += 1
    assert dims == {1, 3} and checked > 50
