"""Live refuses a source whose taxel map is not the scene's design (addon/live.py `_check_map`): a run
streaming the map exported before a module was resized is refused with a message saying what to do; the
map exported after the edit is accepted, and so is one whose only change is its coverage report."""
import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import live
from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.view_stream import ViewPublisher, hello
from skinsafe.core.skin import taxel_map

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)


@pytest.fixture
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")
    assert bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.25, 0, E + 0.05), direction=(-1, 0, 0),
                                         use_cursor=False) == {"FINISHED"}
    return bpy.context.scene


def _attach(path):
    """Attach to a publisher whose hello names the map file at `path` and its hash, as `skinsafe run` does."""
    design = taxel_map.load(path)
    names = [f"j{i}" for i in range(6)]
    pub = ViewPublisher(Tap().latest, hello(design.n_taxels, design.taxels.ids, names, {}, str(path),
                                            taxel_map.sha256(design)), port=0)
    try:
        return bpy.ops.skinsafe.live_attach(source=f"127.0.0.1:{pub.address[1]}")
    finally:
        if live._link is not None:
            assert bpy.ops.skinsafe.live_detach() == {"FINISHED"}
        pub.close()


def test_a_stream_of_another_map_is_refused_naming_the_fix(scene, tmp_path):
    old = tmp_path / "before.json"
    assert bpy.ops.skinsafe.export_taxel_map(filepath=str(old)) == {"FINISHED"}
    assert _attach(old) == {"FINISHED"}
    obj = b2c.module_objects(scene)[0]
    obj.scale = (0.5, 1.0, 1.0)  # 4 columns: ids 32..63 are gone from the scene
    bpy.context.view_layer.update()
    assert b2c.design_of(scene).n_taxels == 32
    with pytest.raises(RuntimeError, match=r"is not this scene's design .*Export this scene's map"):
        _attach(old)
    assert live._link is None and not bpy.app.timers.is_registered(live._timer)
    new = tmp_path / "after.json"
    assert bpy.ops.skinsafe.export_taxel_map(filepath=str(new)) == {"FINISHED"}
    assert _attach(new) == {"FINISHED"}
    assert bpy.ops.skinsafe.coverage() == {"FINISHED"}  # the scene's map gains a coverage report: same taxels
    assert taxel_map.sha256(b2c.design_of(scene)) != taxel_map.sha256(taxel_map.load(new))
    assert _attach(new) == {"FINISHED"}
    assert np.array_equal(taxel_map.load(new).taxels.ids, b2c.design_of(scene).taxels.ids)
