"""Place Skin in the 3D View's toolbar (Object Mode): with the tool active, a left click in the viewport
starts the modal Place Skin operator (addon/place_tool.py), which follows the mouse until the next click."""
import bpy


class SKINSAFE_TL_place_skin(bpy.types.WorkSpaceTool):
    bl_space_type, bl_context_mode = "VIEW_3D", "OBJECT"
    bl_idname = "skinsafe.place_skin_tool"
    bl_label = "Place Skin"
    bl_description = "Click in the viewport, then point at a link: the module follows the mouse (green where it " \
                     "fits, red with the reason); the wheel turns the rows, X mirrors, a click places, Esc leaves"
    bl_icon = "ops.generic.select_circle"
    bl_keymap = (("skinsafe.place_skin", {"type": "LEFTMOUSE", "value": "PRESS"}, None),)


def register():
    bpy.utils.register_tool(SKINSAFE_TL_place_skin, separator=True)


def unregister():
    bpy.utils.unregister_tool(SKINSAFE_TL_place_skin)
