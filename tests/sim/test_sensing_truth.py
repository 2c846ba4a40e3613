"""The sensing ground truth (contact patch over taxel cells) and MuJoCo's native tactile sensor
with several vertices per taxel cell, on the UR5 sample skin."""
import mujoco
import numpy as np
import pytest

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.sim.probes import Truth
from skinsafe.core.sim.readout import TactileReadout
from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene, cell_points, taxel_cell

R = 0.006
PITCH = 0.01


@pytest.fixture(scope="module")
def ur5():
    design = make_sample_design("ur5", pitch=PITCH)
    robot = build_ur5()
    probe = [Obstacle("probe", "sphere", (R,), pos=(0, 0, -5), mocap=True)]
    models = {k: build_scene(design, robot, probe, SceneOptions(tactile_sensors=True, tactile_points=k)).compile()
              for k in (1, 7)}
    pos, frames = TaxelKinematics(models[1], design).poses(robot.home)
    # upper-arm taxels inside a module (four neighbours one pitch away) where a press meets one geom of that link
    up = np.flatnonzero(np.asarray(design.bodies)[design.taxels.body] == "upper_arm_link")
    near = np.linalg.norm(pos[up, None] - pos[None, up], axis=2)
    inner = []
    for i in up[((near > 0) & (near < 1.02 * PITCH)).sum(1) >= 4]:
        data, total = _press(models[1], robot, pos[i], frames[i][:, 2], 0.0005)
        bodies = {models[1].body(models[1].geom_bodyid[g]).name for g in data.contact.geom[:data.ncon].ravel()}
        if total > 0 and data.ncon == 1 and bodies == {"upper_arm_link", "probe"}:
            inner.append(i)
        if len(inner) == 5:
            break
    assert len(inner) == 5
    return design, robot, models, pos, frames, inner


def _press(model, robot, at, normal, depth):
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    data.mocap_pos[0] = at + normal * (R - depth)
    mujoco.mj_forward(model, data)
    f, total = np.zeros(6), 0.0
    for c in range(data.ncon):
        mujoco.mj_contactForce(model, data, c, f)
        total += f[0]
    return data, total


def test_cell_points_fill_each_cell_in_its_plane(ur5):
    design = ur5[0]
    t = design.taxels
    for k in (1, 7, 19):
        pts, owner = cell_points(design, k)
        assert len(pts) == k * len(t) and np.bincount(owner).tolist() == [k] * len(t)
        rel = pts - t.positions[owner]
        assert np.abs(np.einsum("ij,ij->i", rel, t.normals[owner])).max() < 1e-12  # in the taxel's plane
        assert np.linalg.norm(rel, axis=1).max() < 0.5 * taxel_cell(design).max()  # inside the cell
        if k > 1:
            assert np.linalg.norm(rel, axis=1).max() > 0.25 * PITCH  # and filling it


def test_truth_centred_poke_is_one_taxel_with_the_whole_force(ur5):
    design, robot, models, pos, frames, inner = ur5
    model = models[1]
    truth = Truth(model, design, [model.geom("probe").id], probe_radius=R)
    for i in inner[:5]:
        data, total = _press(model, robot, pos[i], frames[i][:, 2], 0.0005)
        f = truth.read(model, data)
        assert np.flatnonzero(f > 0).tolist() == [i] and f[i] == pytest.approx(total, rel=1e-9)


def test_truth_shares_a_poke_between_two_cells_by_its_patch(ur5):
    design, robot, models, pos, frames, inner = ur5
    model = models[1]
    truth = Truth(model, design, [model.geom("probe").id], probe_radius=R)
    i = inner[0]
    x = frames[i][:, 0]
    j = int(np.argmin(np.linalg.norm(pos - (pos[i] + PITCH * x), axis=1)))
    data, total = _press(model, robot, pos[i] + 0.5 * PITCH * x, frames[i][:, 2], 0.002)
    f = truth.read(model, data)
    assert set(np.flatnonzero(f > 0)) == {i, j}  # a = 4.5 mm: the two cells either side of the border
    assert 0.25 < f[i] / total < 0.75 and f.sum() == pytest.approx(total, rel=1e-9)  # shared (the link curves)
    data, total = _press(model, robot, pos[i] + 0.3 * PITCH * x, frames[i][:, 2], 0.002)
    f = truth.read(model, data)
    assert f[i] > f[j] > 0 and f.sum() == pytest.approx(total, rel=1e-9)


def test_tactile_needs_points_in_the_cell_to_feel_an_off_vertex_poke(ur5):
    design, robot, models, pos, frames, inner = ur5
    i = inner[0]
    at = pos[i] + 0.3 * PITCH * frames[i][:, 0]  # the patch (a = 2.4 mm) misses the taxel's own vertex
    for k, lit in ((1, []), (7, [i])):
        model = models[k]
        data, total = _press(model, robot, at, frames[i][:, 2], 0.0005)
        assert total > 0
        f = TactileReadout(model, data, design, per_taxel=k).read(data)
        assert np.flatnonzero(f > 0).tolist() == lit
    data, _ = _press(models[7], robot, pos[i], frames[i][:, 2], 0.0005)
    f = TactileReadout(models[7], data, design, per_taxel=7).read(data)
    assert np.flatnonzero(f > 0).tolist() == [i]  # centred: only its own cell's vertices
