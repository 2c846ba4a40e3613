"""Simulated (MuJoCo) readings through emulated boards: a ball dropped on the UR5 forearm, replayed
by the emulator in its own process, streamed back over ptys and decoded to the same newtons."""
import time

import mujoco
import numpy as np

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety.events import danger_events
from skinsafe.core.sim.readout import SkinReadout
from skinsafe.core.sim.sensor_model import FSRModel
from skinsafe.core.skin.taxel_map import save
from skinsafe.hardware.deploy import deploy
from skinsafe.hardware.emulator import EmulatorProcess
from skinsafe.hardware.stream import SkinStream


def _ball_on_forearm(design, steps=300, every=5):
    """(T, N) taxel forces while a 1 kg ball falls on the forearm of the UR5 at home."""
    spec = build_ur5().spec
    m0 = spec.compile()
    d0 = mujoco.MjData(m0)
    mujoco.mj_resetDataKeyframe(m0, d0, 0)
    mujoco.mj_forward(m0, d0)
    bid = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_BODY, "forearm_link")
    geom = int(np.flatnonzero(m0.geom_bodyid == bid)[0])
    ball = spec.worldbody.add_body(name="ball", pos=d0.geom_xpos[geom] + [0, 0, 0.12])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.03, 0, 0], mass=1.0)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    data.ctrl[:] = data.qpos[:model.nu]  # the position servos hold the arm at home
    readout = SkinReadout(model, design)
    out = []
    for k in range(steps):
        mujoco.mj_step(model, data)
        if k % every == 0:
            out.append(readout.read(data).copy())
    return np.array(out)


def test_simulated_contact_streams_back_as_the_same_forces(tmp_path):
    design = make_sample_design("ur5")
    forces = _ball_on_forearm(design)
    touched = forces.max(axis=0) > 0
    assert forces.max() > 5 and 5 < touched.sum() < 200
    save(design, tmp_path / "skin.json")
    np.save(tmp_path / "sim.npy", forces)
    fsr = FSRModel()
    expected = fsr.decode(fsr.encode(forces))  # what any board sends for these forces, decoded
    with EmulatorProcess([], tmp_path / "flash", "--map", str(tmp_path / "skin.json"),
                         "--replay", str(tmp_path / "sim.npy")) as em:
        ports = {b.id: em.ports[b.uid] for b in design.boards}
        assert [r.status for r in deploy(design, ports)] == ["updated"] * len(design.boards)
        in_danger = np.zeros(design.n_taxels, bool)
        with SkinStream(design, ports, rate_hz=500) as stream:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                u = stream.poll(0.02)
                in_danger |= danger_events({"force": u.peak}, design.taxels.thresholds)
                for s in stream.boards:
                    if s.last_sample is not None:
                        assert np.array_equal(u.force[s.rows], expected[s.last_sample % len(forces), s.rows])
                if all(s.last_sample is not None and s.last_sample >= len(forces) for s in stream.boards):
                    break
        assert u.lost == 0 and u.corrupt == 0
    # every taxel the simulation pushed past its threshold was flagged from the streamed readings, and only those
    assert in_danger.any()
    assert np.array_equal(in_danger, (expected > design.taxels.thresholds["force"]).any(axis=0))
