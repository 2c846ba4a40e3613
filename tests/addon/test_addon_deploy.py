"""Deploy from the add-on (addon/deploy.py) to emulated boards (`skinsafe emulate`'s process on real ptys):
a dry run changes nothing and says each board would update; Deploy writes each board's config (its flash
holds exactly the config of the scene's design, stable taxel ids included); again, each is unchanged; a
board of the design that is not there is named missing (the other one, a fresh board, would update) and the
operator fails; Esc (its Cancel) before the boards are reached sends nothing."""
import hashlib

import bpy
import numpy as np
import pytest

from skinsafe.addon import background, deploy
from skinsafe.addon import blender_to_core as b2c
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.emulator import EmulatorProcess, flash_path

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)


def test_deploy_to_emulated_boards_from_the_addon(tmp_path):
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    scene = bpy.context.scene
    bpy.ops.skinsafe.import_robot(source="ur5")
    assert not bpy.ops.skinsafe.deploy.poll()  # no skin, no boards
    scene.skinsafe.board_capacity = 64
    for x in (-0.3, -0.1):
        bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(x, 0, E + 0.04), direction=(-1, 0, 0),
                                      use_cursor=False)
    design = b2c.design_of(scene)
    assert len(design.boards) == 2 and design.taxels.ids[-1] == (1 << 16) + 63
    dep = bpy.context.window_manager.skinsafe_deploy
    links = tmp_path / "links"
    with EmulatorProcess([(b.uid, b.capacity) for b in design.boards], tmp_path, "--link-dir", str(links)):
        dep.ports = str(links / "board-*")
        assert bpy.ops.skinsafe.deploy(dry_run=True) == {"FINISHED"}
        lines = dep.outcome.splitlines()
        assert len(lines) == 2 and all(": would-update [untouched]" in line for line in lines)
        assert not any(flash_path(tmp_path, b.uid).exists() for b in design.boards)
        # the panel's Deploy: a dry run first, then the confirmation (headless it confirms at once), then Deploy
        assert bpy.ops.skinsafe.deploy("INVOKE_DEFAULT", dry_run=False) == {"FINISHED"}
        assert all(": updated [committed]" in line for line in dep.outcome.splitlines())
        for cfg in board_configs(design):
            assert hashlib.sha256(flash_path(tmp_path, cfg.uid).read_bytes()).digest() == cfg.sha256
            assert np.array_equal(np.sort(cfg.entries["taxel_id"]), np.sort(design.taxels.ids[design.taxels.board
                                                                                             == cfg.board_id]))
        assert bpy.ops.skinsafe.deploy(dry_run=False) == {"FINISHED"}
        assert all(": unchanged" in line for line in dep.outcome.splitlines())
    with EmulatorProcess([(b.uid, b.capacity) for b in design.boards], tmp_path / "esc", "--link-dir",
                         str(tmp_path / "l2")):
        cancel = background.Cancel()
        cancel.requested = True  # Esc before the boards were reached: nothing is sent
        reports = deploy.run(design, [str(tmp_path / "l2" / "board-*")], False, cancel)
        assert [r.ok for r in reports] == [False, False] and all("interrupted by Esc" in r.line() for r in reports)
        assert not any(flash_path(tmp_path / "esc", b.uid).exists() for b in design.boards)
    with EmulatorProcess([(design.boards[0].uid, 64)], tmp_path / "one", "--link-dir", str(tmp_path / "l1")):
        dep.ports = str(tmp_path / "l1" / "board-*")
        with pytest.raises(RuntimeError, match=r"1 of 2 boards not checked; the first: board 1 .*missing"):
            bpy.ops.skinsafe.deploy(dry_run=True)
        assert ": would-update" in dep.outcome.splitlines()[0] and ": missing" in dep.outcome.splitlines()[1]
