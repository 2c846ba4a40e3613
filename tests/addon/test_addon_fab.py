"""File > Export > skinsafe FPC fabrication, headless: the design in the scene becomes FOLDER/fab with one KiCad
board per module whose taxel footprints are the design's taxels; an unwritable folder is refused in one report."""
import json
import re

import bpy
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import export

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)


def test_fab_export_writes_the_scene_design(tmp_path):
    assert (export.SKINSAFE_OT_export_fab, "skinsafe FPC fabrication (folder)") in export.EXPORTS
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    assert not bpy.ops.skinsafe.export_fab.poll()  # no skin
    bpy.ops.skinsafe.import_robot(source="ur5")
    bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.25, 0, E + 0.05), direction=(-1, 0, 0),
                                  use_cursor=False)
    assert bpy.ops.skinsafe.export_fab(directory=str(tmp_path)) == {"FINISHED"}
    design = b2c.design_of(bpy.context.scene)
    index = json.loads((tmp_path / "fab" / "fab.json").read_text())
    (entry,) = index["modules"]
    assert entry["pads"] == design.n_taxels and entry["link"] == "forearm_link"
    board = (tmp_path / "fab" / entry["files"]["kicad_pcb"]).read_text()
    refs = re.findall(r'\(fp_text reference "T(\d+)"', board)
    assert sorted(map(int, refs)) == sorted(design.taxels.ids.tolist())
    assert "wrote" in bpy.context.scene.skinsafe.message and "1 FPC module," in bpy.context.scene.skinsafe.message
    with pytest.raises(RuntimeError, match="Permission denied|not a directory|No such file|Read-only"):
        bpy.ops.skinsafe.export_fab(directory="/proc/skin")
