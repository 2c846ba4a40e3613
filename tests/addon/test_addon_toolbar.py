"""Place Skin in the 3D View's toolbar (addon/toolbar.py): registered with the add-on, selectable in
Object Mode (headless bpy has a window and a 3D View's tool system), removed by unregister."""
import bpy
from bl_ui.space_toolsystem_common import ToolSelectPanelHelper

from skinsafe.addon import toolbar

TOOL = "skinsafe.place_skin_tool"


def _object_mode_tools() -> dict:
    cls = ToolSelectPanelHelper._tool_class_from_space_type("VIEW_3D")
    return {t.idname: t for t in cls._tools_flatten(cls.tools_from_context(bpy.context, mode="OBJECT")) if t}


def test_the_toolbar_tool_starts_place_skin_on_a_click_and_unregisters():
    tool = _object_mode_tools()[TOOL]
    assert tool.label == "Place Skin"
    (name,) = tool.keymap  # the keymap register_tool made in the add-ons' key configuration
    km = bpy.context.window_manager.keyconfigs.addon.keymaps[name]
    assert [(k.idname, k.type, k.value) for k in km.keymap_items] == [("skinsafe.place_skin", "LEFTMOUSE", "PRESS")]
    assert bpy.ops.wm.tool_set_by_id(name=TOOL, space_type="VIEW_3D") == {"FINISHED"}
    assert bpy.context.workspace.tools.from_space_view3d_mode("OBJECT").idname == TOOL
    toolbar.unregister()
    assert TOOL not in _object_mode_tools() and name not in bpy.context.window_manager.keyconfigs.addon.keymaps
    toolbar.register()  # the add-on's unregister (conftest) removes it again
    assert TOOL in _object_mode_tools()
