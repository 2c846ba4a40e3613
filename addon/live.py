"""Live link (View3D > N > Skin > Live): colour the designed taxels by what the skin feels, on the robot in
the viewport, from a running `skinsafe run --view` (its view stream, HOST:PORT) or a record (a `run --record` folder, or FILE.mcap).

Each module mesh gets a colour attribute `live` (one colour per taxel face, on the web page's scale:
core/runtime/view_scale.py; grey: no reading, or a taxel the source does not have), matched by taxel id,
so a map whose taxels are in another order, or a scene with only some of the map's modules, colours the
right faces; a source whose taxel map is not the scene's design (its `map_sha256`, then its taxels) is
refused on attach, naming what to do. The robot takes the measured pose; a record's obstacles (an experiment's balls, a person's
parts) are drawn in the collection "skinsafe live obstacles" and move with its ticks. `step(scene)` applies the newest frame: callable without
Blender's event loop (headless, bpy timers never fire); the Attach operator registers a timer that calls
it, Detach (and unregistering the add-on) removes it (a bpy process hangs at exit with a timer left).

Imports: bpy, numpy and the stream client (stdlib + numpy): nothing beyond the add-on's bundled wheels; a
record is read lazily (mcap, mcap-ros2-support, lz4).
"""
from __future__ import annotations

import time

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, StringProperty

from skinsafe.core.runtime.rosbag2 import is_record
from skinsafe.core.runtime.view_scale import colours, default_vmax
from skinsafe.core.runtime.view_stream import StreamError, ViewClient

ATTR = "live"
FPS = 20.0
OBSTACLES = "skinsafe live obstacles"  # the collection of a record's obstacles (an experiment's balls, a person)
OBSTACLE_RGBA = (230 / 255, 150 / 255, 60 / 255, 0.6)  # the page's colour
_link = None  # the one attached source: a _Link


class _Link:
    """An attached source: `frame(t)` gives (header, forces) of the newest frame (live) or the tick at t (record)."""

    def __init__(self, source: str):
        self.source, self.client, self.record = source, None, None
        if is_record(source):
            from skinsafe.core.runtime.recording import Recording
            from skinsafe.core.skin.taxel_map import load

            self.record = Recording(source)
            self.ids = load(self.record.config["map"]).taxels.ids
            self.joint_names = list(self.record.config["joint_names"])
            self.t0, self.t1 = float(self.record.t[0]), float(self.record.t[-1])
        else:
            host, _, port = source.rpartition(":")
            try:
                self.client = ViewClient(host or "127.0.0.1", int(port))
            except ValueError:
                raise StreamError(f"{source!r}: give HOST:PORT of `skinsafe run --view` or a record FILE.mcap") from None
            self.ids, self.joint_names = self.client.ids, list(self.client.hello["joint_names"])
        self.obstacles = []  # a record's obstacle objects (None: a kind not drawn)
        self.last = None  # the header last applied
        self.wall = None  # a playing record: the wall clock of the last step
        self.faces = None  # (the design revision, `_faces` of it)

    def close(self) -> None:
        if self.client is not None:
            self.client.close()


def _faces(scene, ids: np.ndarray) -> list[tuple]:
    """Per module object: (object, index of each of its taxels in the source's order, -1: not in the source)."""
    from skinsafe.addon.blender_to_core import design_of

    design = design_of(scene)
    if design is None:
        return []
    at = {int(i): k for k, i in enumerate(ids)}
    out = []
    for obj in scene.objects:
        mm = obj.skinsafe_module
        if mm.is_module:
            taxels = design.taxels.ids[design.taxels.module == mm.module_id]
            if len(obj.data.polygons) == len(taxels):
                out.append((obj, np.array([at.get(int(i), -1) for i in taxels], np.intp)))
    return out


def _linear(rgb: np.ndarray) -> np.ndarray:
    from skinsafe.addon.core_to_blender import srgb_to_linear

    return srgb_to_linear(rgb / 255.0)


def colour(scene, force: np.ndarray, ids: np.ndarray, vmax: float | None = None, faces=None) -> int:
    """Write forces (N, in the order of taxel `ids`) to every module's `live` attribute (`faces`: `_faces(scene,
    ids)`, if known); the modules changed."""
    from skinsafe.addon.blender_to_core import design_of

    design = design_of(scene)
    top = vmax or default_vmax(design.taxels.thresholds.get("force", ()) if design is not None else ())
    rgba = np.ones((len(force) + 1, 4), np.float32)  # the last row: no reading (a taxel the source lacks)
    rgba[:, :3] = _linear(colours(np.append(np.asarray(force, float), np.nan), top))
    changed = 0
    for obj, idx in faces if faces is not None else _faces(scene, ids):
        c = np.repeat(rgba[idx], 6, axis=0)  # six corners per taxel hexagon
        me = obj.data
        attr = me.color_attributes.get(ATTR) or me.color_attributes.new(ATTR, "FLOAT_COLOR", "CORNER")
        old = np.empty(len(c) * 4, np.float32)
        attr.data.foreach_get("color", old)
        if not np.array_equal(old, c.ravel()):
            attr.data.foreach_set("color", c.ravel())
            changed += 1
        me.color_attributes.active_color = attr
        me.color_attributes.render_color_index = me.color_attributes.find(ATTR)
        me.update()
    return changed


def _pose(scene, q, names) -> None:
    from skinsafe.addon.core_to_blender import apply_pose

    joints = scene.skinsafe.joints
    moved = False
    for n, v in zip(names, q):
        if n in joints and abs(joints[n].value - v) > 1e-9:
            joints[n]["value"] = float(v)  # no update callback per joint: one pose below
            moved = True
    if moved:
        apply_pose(scene)


def attach(scene, source: str) -> str:
    """Attach to `source` (HOST:PORT or FILE.mcap); the line the panel shows."""
    global _link
    detach(scene)
    _link = _Link(source)
    named = _link.record.config if _link.record is not None else _link.client.hello  # the map the source runs
    try:
        _check_map(scene, source, named.get("map_sha256", ""), named.get("map", ""))
    except StreamError:
        detach(scene)
        raise
    n = len(_faces(scene, _link.ids))
    if not n:
        detach(scene)
        raise StreamError(f"{source}: none of the scene's modules has taxels of this source's map (matched by taxel "
                          "id); open the design the run uses")
    lv = bpy.context.window_manager.skinsafe_live
    msg = f"attached to {source}: {n} module(s) matched" + (
        f"; a record of {_link.t1 - _link.t0:.2f} s" if _link.record is not None else "")
    if _link.record is not None:
        _link.obstacles = _add_obstacles(scene, _link.record.config.get("obstacles") or ())
        lv["time"] = _link.t0  # no callback: shown here
        show_time(scene, _link.t0)
    lv.status = msg
    return msg


def _check_map(scene, source: str, sha: str, path: str) -> None:
    """Refuse a source whose taxel map is not the scene's design (its hash, or its taxels where the map file
    is here to read: a map whose only change is its coverage report passes). A source naming no map hash
    is matched by taxel id alone."""
    from skinsafe.addon.blender_to_core import design_of
    from skinsafe.core.skin import taxel_map
    from skinsafe.core.skin.model import DesignError

    design = design_of(scene)
    if not sha or design is None:
        return
    mine = taxel_map.sha256(design)
    if sha == mine:
        return
    try:
        other = taxel_map.load(path) if path else None
    except DesignError:
        other = None
    t = design.taxels
    if other is not None and other.bodies == design.bodies and all(
            np.array_equal(getattr(other.taxels, k), getattr(t, k)) for k in ("ids", "module", "body", "positions",
                                                                            "frames")):
        return
    raise StreamError(f"{source}: its taxel map ({path or 'no file named'}, sha256 {sha[:12]}) is not this scene's "
                      f"design (sha256 {mine[:12]}): its taxels would light the wrong places. Export this scene's map "
                      "(File > Export > skinsafe Taxel Map) and restart the run with it, or open the .blend that map "
                      "was designed in")


def _add_obstacles(scene, obstacles) -> list:
    """A record's obstacles as meshes in their own collection, where its metadata puts them (MuJoCo primitives:
    core/runtime/sim_record.py); the objects (None: a kind not drawn)."""
    from skinsafe.core.runtime.sim_record import obstacle_mesh

    if not obstacles:
        return []
    col = bpy.data.collections.new(OBSTACLES)
    scene.collection.children.link(col)
    out = []
    for i, ob in enumerate(obstacles):
        mesh = obstacle_mesh(ob)
        if mesh is None:
            out.append(None)
            continue
        me = bpy.data.meshes.new(f"obstacle{i}")
        me.from_pydata(mesh[0].tolist(), [], mesh[1].tolist())
        me.update()
        obj = bpy.data.objects.new(f"obstacle{i}", me)
        obj.rotation_mode, obj.color = "QUATERNION", OBSTACLE_RGBA
        col.objects.link(obj)
        _place(obj, np.r_[ob["pos"], ob.get("quat", (1.0, 0.0, 0.0, 0.0))])
        out.append(obj)
    return out


def _place(obj, pose) -> None:
    """An obstacle at `pose`: position (3), quaternion w x y z (4)."""
    obj.location, obj.rotation_quaternion = tuple(pose[:3]), tuple(pose[3:7])


def _remove_obstacles() -> None:
    col = bpy.data.collections.get(OBSTACLES)
    if col is None:
        return
    for obj in list(col.objects):
        me = obj.data
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(me)
    bpy.data.collections.remove(col)


def step(scene) -> bool:
    """Apply the newest frame (live) or advance a playing record; whether something was applied."""
    if _link is None:
        return False
    lv = bpy.context.window_manager.skinsafe_live
    if _link.record is not None:
        if not lv.playing:
            _link.wall = None
            return False
        now = time.monotonic()
        t = min(lv.time + (now - (_link.wall or now)), _link.t1)
        _link.wall, lv["time"] = now, t
        lv.playing = t < _link.t1
        return show_time(scene, t)
    newest = _link.client.poll()
    if newest is None:
        if _link.client.closed:
            lv.status = f"{_link.source}: the stream ended (the run stopped); last t = " + (
                f"{_link.last['t']:.3f} s" if _link.last else "none")
        return False
    _apply(scene, *newest)
    return True


def show_time(scene, t: float) -> bool:
    """A record's tick nearest to t (s)."""
    if _link is None or _link.record is None:
        return False
    _apply(scene, *_link.record.frame(_link.record.index(t)))
    return True


def _apply(scene, h: dict, force: np.ndarray) -> None:
    lv = bpy.context.window_manager.skinsafe_live
    _pose(scene, h["q"], _link.joint_names)
    rev = scene.skinsafe.design_rev
    if _link.faces is None or _link.faces[0] != rev:  # the design changed: match its taxels again
        _link.faces = (rev, _faces(scene, _link.ids))
    colour(scene, force, _link.ids, lv.vmax or None, _link.faces[1])
    for obj, pose in zip(_link.obstacles, h.get("obstacles") or ()):  # a person who moves
        if obj is not None:
            _place(obj, pose)
    _link.last = h
    f = np.nan_to_num(force)
    top = int(np.argmax(f)) if len(f) else -1
    lv.status = (f"t = {h['t']:.3f} s" + (f", largest {f[top]:.2f} N (taxel id {int(_link.ids[top])})"
                                          if top >= 0 and f[top] > 0 else ", no touch")
                 + (" · RETRACTING" if h.get("retracting") else "") + (f" · STOPPED: {h['stop']}" if h.get("stop") else ""))


def detach(scene=None) -> None:
    """Close the source and remove the timer; the modules show their design colours again."""
    global _link
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
    if _link is not None:
        _link.close()
        _link = None
    _remove_obstacles()
    for obj in (scene.objects if scene is not None else ()):
        me = obj.data if obj.skinsafe_module.is_module else None
        if me is not None and "heat" in me.color_attributes:
            me.color_attributes.active_color = me.color_attributes["heat"]
            me.color_attributes.render_color_index = me.color_attributes.find("heat")


def _timer():
    if _link is None:
        return None
    try:
        step(bpy.context.scene)
    except Exception as e:  # the timer must not raise into Blender's loop: said in the panel, then detached
        bpy.context.window_manager.skinsafe_live.status = f"detached: {e}"
        detach(bpy.context.scene)
        return None
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PROPERTIES") or area.ui_type == "VIEW_3D":
                area.tag_redraw()
    return 1.0 / FPS


def _time_changed(self, context):
    if _link is not None and _link.record is not None:
        show_time(context.scene, self.time)


class SkinsafeLive(bpy.types.PropertyGroup):
    source: StringProperty(name="Source", default="127.0.0.1:8790",
                           description="HOST:PORT of `skinsafe run --view` (its view stream), or a record FILE.mcap")
    vmax: FloatProperty(name="Scale top (N)", default=0.0, min=0.0, description="0: twice the largest threshold")
    time: FloatProperty(name="Time (s)", default=0.0, update=_time_changed, description="a record's time")
    playing: BoolProperty(name="Play", default=False)
    status: StringProperty(default="")


class SKINSAFE_OT_live_attach(bpy.types.Operator):
    """Colour the skin live from a running `skinsafe run --view` (HOST:PORT) or a record (FILE.mcap)"""

    bl_idname = "skinsafe.live_attach"
    bl_label = "Attach"

    source: StringProperty(name="Source", description="default: the panel's")

    @classmethod
    def poll(cls, context):
        return any(o.skinsafe_module.is_module for o in context.scene.objects)

    def execute(self, context):
        lv = context.window_manager.skinsafe_live
        src = self.source or lv.source
        try:
            msg = attach(context.scene, bpy.path.abspath(src) if is_record(bpy.path.abspath(src)) else src)
        except (StreamError, ValueError, OSError) as e:
            lv.status = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        lv.source = src
        for area in context.screen.areas if context.screen else ():
            for space in area.spaces:
                if space.type == "VIEW_3D":
                    space.shading.color_type = "VERTEX"
        bpy.app.timers.register(_timer, first_interval=0.0)
        self.report({"INFO"}, msg)
        return {"FINISHED"}


class SKINSAFE_OT_live_detach(bpy.types.Operator):
    """Stop colouring the skin live"""

    bl_idname = "skinsafe.live_detach"
    bl_label = "Detach"

    poll = classmethod(lambda cls, context: _link is not None)

    def execute(self, context):
        detach(context.scene)
        context.window_manager.skinsafe_live.status = "detached"
        return {"FINISHED"}


class SKINSAFE_PT_live(bpy.types.Panel):
    bl_space_type, bl_region_type, bl_category = "VIEW_3D", "UI", "Skin"
    bl_idname = "SKINSAFE_PT_live"
    bl_label = "Live"

    def draw(self, context):
        lv, col = context.window_manager.skinsafe_live, self.layout.column()
        col.prop(lv, "source")
        row = col.row(align=True)
        row.operator("skinsafe.live_attach")
        row.operator("skinsafe.live_detach")
        col.prop(lv, "vmax")
        if _link is not None and _link.record is not None:
            col.prop(lv, "time", slider=True)
            col.prop(lv, "playing", toggle=True)
        if lv.status:
            col.label(text=lv.status)


CLASSES = (SkinsafeLive, SKINSAFE_OT_live_attach, SKINSAFE_OT_live_detach, SKINSAFE_PT_live)
_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()
    bpy.types.WindowManager.skinsafe_live = bpy.props.PointerProperty(type=SkinsafeLive)


def unregister():
    detach(bpy.context.scene if hasattr(bpy.context, "scene") else None)
    del bpy.types.WindowManager.skinsafe_live
    _unregister()
