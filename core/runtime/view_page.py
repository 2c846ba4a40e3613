"""The live view's web page (viser): the robot in its measured pose, every taxel coloured by its reading,
the retracting taxels with their motion, the layers' states over time, board health, a timeline.

The geometry is the robot's MuJoCo model (each body's visual surface, `core/design/surface.body_surface`:
meshes and primitives as the scene has them) with the skin's taxels as one point cloud per body, in the
body frame: a frame moves only the bodies (poses from MuJoCo kinematics at the measured q) and sends
the colours of the bodies whose taxels changed. `show(header, forces)` draws one tick of the view
stream's format (core/runtime/view_stream.py); the caller decides which and how often. A record's
obstacles (MuJoCo primitives: an experiment's balls, a person's parts) are drawn where its metadata puts
them, and moved to a tick's `obstacles` poses where the header has them (a person who moves).

Colour scale (labelled on the page): force in N from 0 to `vmax` (default twice the largest taxel
threshold), dark blue -> red at the threshold -> yellow; grey: no fresh reading (excluded, silent board).
"""
from __future__ import annotations

import html
import threading
from collections import deque

import mujoco
import numpy as np
import viser

from skinsafe.core.design.surface import body_surface
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.runtime.sim_record import obstacle_mesh
from skinsafe.core.runtime.view_scale import COLOURS, STOPS, colours, default_vmax

ROBOT_RGB = (185, 188, 195)
ARROW_RGB = (0, 200, 220)
OBSTACLE_RGB = (230, 150, 60)
ARROW_M = 0.06  # length of a retracting taxel's arrow, m
HISTORY_S = 10.0
VIEW_DIR = np.array([0.55, -0.7, 0.45])  # the page's first view: from the front right, above
FOV = np.radians(75.0)  # vertical field of view (viser's)


def camera(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(eye, look-at) of the page's first view: along VIEW_DIR, far enough to see all `points` (the skin)."""
    at = (points.min(0) + points.max(0)) / 2
    radius = float(np.linalg.norm(points.max(0) - points.min(0))) / 2
    return at + VIEW_DIR / np.linalg.norm(VIEW_DIR) * 2.0 * radius, at  # seconds of layer states on the live plot


def skin_bodies(model: mujoco.MjModel, kin: TaxelKinematics):
    """(body id, name, visual surface or None, its taxels) of every body with a surface or taxels."""
    for b in range(1, model.nbody):
        name = model.body(b).name
        taxels = np.flatnonzero(kin.body_id == b)
        try:
            surf = body_surface(model, name)
        except ValueError:
            surf = None
        if surf is not None or len(taxels):
            yield b, name, surf, taxels


def point_size(design) -> float:
    """A taxel's point size on the page, m: 1.3 times the modules' median pitch (1 cm without one)."""
    pitches = [m.pitch for m in design.modules if getattr(m, "pitch", 0)]
    return float(np.clip(1.3 * (np.median(pitches) if pitches else 0.01), 0.003, 0.025))


def scale_html(vmax: float, threshold: float) -> str:
    """The labelled colour bar (HTML)."""
    grad = ", ".join(f"rgb({int(r)},{int(g)},{int(b)}) {s * 100:.0f}%" for s, (r, g, b) in zip(STOPS, COLOURS))
    ticks = "".join(f"<span style='position:absolute;left:{v / vmax * 100:.1f}%;transform:translateX(-50%)'>{v:g}</span>"
                    for v in np.linspace(0, vmax, 5))
    return (f"<div style='font-size:0.8em;padding:0 0.5em'><b>taxel force, N</b> (threshold {threshold:g} N; "
            f"<span style='color:rgb(150,150,150)'>grey</span>: no reading)"
            f"<div id='skinsafe-scale' style='height:12px;border-radius:3px;background:linear-gradient(to right, {grad})'></div>"
            f"<div style='position:relative;height:1.2em'>{ticks}</div></div>")


def _wxyz(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q


class Page:
    """One viser server showing one robot and skin. `timeline`: (t0, t1, step) of a record (a slider and
    play/next-contact buttons call `on_time(t)`), or None for a live stream."""

    def __init__(self, design, model: mujoco.MjModel, host: str = "127.0.0.1", port: int = 8080,
                 vmax: float | None = None, title: str = "skinsafe", boards: dict | None = None,
                 timeline: tuple | None = None, on_time=None, on_next_contact=None, obstacles=(), q0=None,
                 board_period_s: float = 0.0):
        self.design, self.model = design, model
        self.kin = TaxelKinematics(model, design)
        self.data = self.kin.data
        top = default_vmax(design.taxels.thresholds.get("force", ()))
        self.threshold, self.vmax = top / 2, float(vmax or top)
        self.boards = {str(k): v for k, v in (boards or {}).items()}
        self.late_ms = 2e3 * board_period_s  # a board's frame older than this: the silence watchdog's limit
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        sc = self.server.scene
        sc.set_up_direction("+z")
        sc.add_grid("/ground", width=2.0, height=2.0, cell_size=0.1, position=(0.0, 0.0, 0.0))
        self.point_size = point_size(design)
        self.bodies = {}  # body id -> frame handle
        self.clouds = {}  # body id -> (point cloud handle, taxel indices)
        t = design.taxels
        for b, name, surf, taxels in skin_bodies(model, self.kin):
            frame = sc.add_frame(f"/robot/{name}", show_axes=False)
            self.bodies[b] = frame
            if surf is not None:
                sc.add_mesh_simple(f"/robot/{name}/mesh", surf.vertices.astype(np.float32),
                                   surf.triangles.astype(np.uint32), color=ROBOT_RGB)
            if len(taxels):
                lifted = t.positions[taxels] + 0.0015 * t.frames[taxels, :, 2]
                pc = sc.add_point_cloud(f"/robot/{name}/taxels", lifted.astype(np.float32),
                                        colors=colours(np.zeros(len(taxels)), self.vmax),
                                        point_size=self.point_size,
                                        point_shape="circle", precision="float32")
                self.clouds[b] = (pc, taxels, None)
        self.obstacles = [self._obstacle(i, ob) for i, ob in enumerate(obstacles)]  # handles (None: not drawn)
        self.arrows = None
        self._lock = threading.Lock()
        self._history = deque()  # (t, retracting, speed factor, potential) of the live stream
        self._shown_t = None
        eye, at = camera(self.kin.poses(q0 if q0 is not None else self.data.qpos.copy())[0])
        self.server.initial_camera.position, self.server.initial_camera.look_at = tuple(eye), tuple(at)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self._gui(timeline, on_time, on_next_contact)

    def _obstacle(self, i: int, ob: dict):
        mesh = obstacle_mesh(ob)
        if mesh is None:
            return None
        v, tri = mesh
        return self.server.scene.add_mesh_simple(f"/world/obstacle{i}", v.astype(np.float32), tri.astype(np.uint32),
                                                 color=OBSTACLE_RGB, opacity=0.6, position=tuple(ob["pos"]),
                                                 wxyz=tuple(ob.get("quat", (1.0, 0.0, 0.0, 0.0))))

    # -- the panel -------------------------------------------------------------------------------
    def _gui(self, timeline, on_time, on_next_contact) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        self.status = gui.add_markdown("**waiting for the first tick**")
        gui.add_html(scale_html(self.vmax, self.threshold))
        self.slider, self.on_time = None, on_time
        if timeline is not None:
            t0, t1, step = timeline
            with gui.add_folder("Timeline"):
                self.slider = gui.add_slider("time (s)", min=round(t0, 4), max=round(t1, 4), step=step,
                                             initial_value=round(t0, 4))
                row = gui.add_button_group("play", ("play", "pause", "next contact"))
                self.playing = False

                @self.slider.on_update
                def _(_ev):
                    if on_time is not None:
                        on_time(float(self.slider.value))

                @row.on_click
                def _(ev):
                    if ev.target.value == "play":
                        self.playing = True
                    elif ev.target.value == "pause":
                        self.playing = False
                    elif on_next_contact is not None:
                        self.playing = False
                        t = on_next_contact(float(self.slider.value))
                        if t is not None:
                            self.goto(t)
        with gui.add_folder("Layers"):
            self.layers = gui.add_markdown("")
            self.plot = gui.add_uplot(data=(np.zeros(1), np.zeros(1), np.ones(1), np.zeros(1)),
                                      series=(viser.uplot.Series(label="t, s"),
                                              viser.uplot.Series(label="retracting", stroke="red", width=2),
                                              viser.uplot.Series(label="speed factor", stroke="blue", width=2),
                                              viser.uplot.Series(label="danger potential f", stroke="orange",
                                                                 width=2)),
                                      scales={"x": viser.uplot.Scale(time=False, auto=True)},
                                      title="layers over time (t, s)", aspect=2.0)
        with gui.add_folder("Boards"):
            self.board_md = gui.add_markdown("")

    def goto(self, t: float) -> None:
        """Move the timeline to `t` and draw that tick (a value set here does not call the slider's callback)."""
        self.slider.value = round(t, 4)
        self.on_time(float(self.slider.value))

    def plot_series(self, t, retracting, factor, potential) -> None:
        """The layers' states over time (a whole record, or the live history)."""
        self.plot.data = tuple(np.asarray(x, float) for x in (t, retracting, np.minimum(factor, 2.0), potential))

    # -- one tick --------------------------------------------------------------------------------
    def watched(self) -> bool:
        """A browser has the page open."""
        return bool(self.server.get_clients())

    def show(self, h: dict, force: np.ndarray, live: bool = False) -> None:
        """Draw one tick (`h`: a view-stream frame header; `force`: (N,) taxel forces)."""
        with self._lock, self.server.atomic():
            q = np.asarray(h["q"], float)
            self.data.qpos[:len(q)] = q
            mujoco.mj_kinematics(self.model, self.data)
            for b, frame in self.bodies.items():
                frame.position = self.data.xpos[b].copy()
                frame.wxyz = self.data.xquat[b].copy()
            rgb = colours(force, self.vmax)
            for b, (pc, idx, last) in list(self.clouds.items()):
                c = rgb[idx]
                if last is None or not np.array_equal(c, last):
                    pc.colors = c
                    self.clouds[b] = (pc, idx, c)
            for node, pose in zip(self.obstacles, h.get("obstacles") or ()):
                if node is not None:
                    node.position, node.wxyz = tuple(pose[:3]), tuple(pose[3:])
            self._arrows(h, q)
            self._panel(h, force)
            if live:
                self._live_history(h)
            self._shown_t = h["t"]

    def _arrows(self, h: dict, q: np.ndarray) -> None:
        pool = np.asarray(h.get("pool") or [], np.intp)
        if not len(pool):
            if self.arrows is not None:
                self.arrows.visible = False
            return
        J, pos, frames = self.kin.jacobians_of(pool, q)
        v = np.einsum("kij,j->ki", J[:, :3], np.asarray(h["command"], float))
        speed = np.linalg.norm(v, axis=1, keepdims=True)
        d = np.where(speed > 1e-6, v / np.maximum(speed, 1e-12), -frames[:, :, 2])  # at rest: along -n
        tip = pos - 1.5 * self.point_size * d  # outside the skin, pointing at the taxel (which stays in sight)
        pts = np.stack([tip - ARROW_M * d, tip], 1).astype(np.float32)
        if self.arrows is not None:
            self.arrows.remove()
        self.arrows = self.server.scene.add_arrows("/contacts", pts, colors=ARROW_RGB, shaft_radius=0.003,
                                                   head_radius=0.008, head_length=0.015)

    def _panel(self, h: dict, force: np.ndarray) -> None:
        f = np.nan_to_num(force, nan=0.0)
        hot = int((f > self.design.taxels.thresholds["force"]).sum()) if "force" in self.design.taxels.thresholds else 0
        top = int(np.argmax(f)) if len(f) else -1
        stop = h.get("stop") or ""
        self.status.content = (f"**t = {h['t']:.3f} s**, tick {h.get('seq', '')} · "
                               + (f"**STOPPED**: {html.escape(stop)}" if stop else "running")
                               + f" · {hot} taxel(s) over threshold"
                               + (f", largest {f[top]:.2f} N on taxel {top}" if top >= 0 and f[top] > 0 else ""))
        pool = h.get("pool") or []
        flags = ", ".join(h.get("flags") or []) or "none"
        retr = (f"**retraction: ACTIVE**, {len(pool)} taxel(s) retracting (first {pool[0]})" if h.get("retracting")
                else "**retraction:** idle")
        self.layers.content = "\n\n".join([
            retr,
            f"**speed factor** {h.get('speed_factor', 1.0):.3f} (|command| / |planned|)",
            f"**danger potential f** {h.get('potential', 0.0):.3f} (strategy/modulation TDM; 0 without --tdm)",
            f"**flags** {html.escape(flags)}",
            "**watchdog** " + (f"STOPPED: {html.escape(stop)}" if stop else "ok"),
            "**command** " + " ".join(f"{v:+.3f}" for v in h.get("command") or []) + " rad/s"])
        ages = h.get("board_age_ms") or {}
        rows = ["| board | uid | last frame | |", "| --- | --- | ---: | --- |"]
        for uid, age in sorted(ages.items(), key=lambda kv: int(kv[0])):
            name = self.boards.get(str(uid), "")
            rows.append(f"| {html.escape(name)} | {int(uid):#x} | {age:.1f} ms | {self._health(age)} |")
        rows.append(f"\nframes lost: {h.get('frames_lost', 0)}")
        self.board_md.content = "\n".join(rows) if ages else "no board data (simulation record)"

    def _health(self, age_ms: float) -> str:
        return "" if not self.late_ms else "ok" if age_ms <= self.late_ms else "LATE"

    def _live_history(self, h: dict) -> None:
        hist = self._history
        hist.append((h["t"], float(h.get("retracting", False)), h.get("speed_factor", 1.0), h.get("potential", 0.0)))
        while hist and hist[0][0] < h["t"] - HISTORY_S:
            hist.popleft()
        if len(hist) % 5 == 0 or len(hist) < 5:
            self.plot_series(*np.array(hist).T)

    def close(self) -> None:
        self.server.stop()
