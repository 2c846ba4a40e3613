"""`skinsafe bench viewers`: the live view's two candidates at 16,384 taxels, in headless Chromium (Debian's).

One row per viewer, each serving the same scene from this process: the UR5 sample skin cut to `--taxels`
(whole modules, core/bench/runtime.sample_skin), every body's mesh posed by q, the taxels as points whose
colours all change on every update, pushed at `--hz` (30: the view stream's rate):
- `viser`: the page `skinsafe view` serves (core/runtime/view_page.Page, its `show` per update);
- `rerun`: Rerun's web viewer (rerun-sdk, only where it is installed: not a skinsafe dependency) fed the
  same meshes, transforms and colours (`rr.log`, partial updates of the colours), served by
  `rr.serve_grpc` + `rr.serve_web_viewer`.
Figures: page_load_s (navigation -> the skin drawn: its all-yellow first frame on the canvas), render_fps
(frames the page drew per second while updates stream in: distinct requestAnimationFrame times over
`--seconds`), latency_ms_p50 / max (the source turns every taxel yellow -> a screenshot shows it; the
screenshot's own time included, the same for both), server_ms_p50 / p99 (the source's cost of one update:
`Page.show` / the `rr.log` calls), server_cpu (this process's CPU seconds per wall second while streaming:
the viewer's server threads), load_average (the machine's, shared).
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import threading
import time
from importlib.metadata import PackageNotFoundError, version

import numpy as np

from skinsafe.core.bench.browser import CHROMIUM_ARGS, require_chromium

W, H = 1200, 800
DRAWN, COOL = 5000, 2000  # yellow pixels: the skin drawn all yellow / none of it yellow (the scale bar has ~600)
FATAL = re.compile(r"Failed to start|has crashed|panicked|WebGL.*(not supported|unavailable)", re.I)
WEBGPU_ARGS = ["--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-webgpu-adapter=swiftshader"]
# counts the frames the page draws: distinct requestAnimationFrame timestamps
COUNT_FRAMES = """(() => { const raf = window.requestAnimationFrame.bind(window); window.__frames = 0; let last = -1;
  window.requestAnimationFrame = (cb) => raf((t) => { if (t !== last) { last = t; window.__frames++; } cb(t); }); })();"""


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, default=16384)
    p.add_argument("--hz", type=float, default=30.0, help="updates per second the source pushes")
    p.add_argument("--seconds", type=float, default=10.0, help="frame-rate window")
    p.add_argument("--trials", type=int, default=5, help="latency trials per viewer")
    p.add_argument("--viewers", nargs="+", default=["viser", "rerun", "rerun-webgpu"],
                   choices=("viser", "rerun", "rerun-webgpu"), help="rerun-webgpu: Chromium with its (unsafe, "
                   "software) WebGPU adapter, which Rerun's viewer prefers to WebGL")
    p.add_argument("--port", type=int, default=8470, help="first of the ports used (viser; rerun: +1, +2)")


def yellow(png: bytes) -> int:
    """Pixels of the scale's top colour (255, 240, 90) in a screenshot."""
    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return int(((a[..., 0] > 200) & (a[..., 1] > 190) & (a[..., 2] < 150)).sum())


class Source:
    """Pushes updates at `hz` from a thread: `mode` "yellow" (every taxel at the top of the scale) or "cool"
    (random forces in the scale's lower 40%: no yellow), q swaying; `push(q, force)` is the viewer's."""

    def __init__(self, push, q0: np.ndarray, n: int, vmax: float, hz: float):
        self.push, self.q0, self.n, self.vmax, self.period = push, q0, n, vmax, 1.0 / hz
        self.mode, self.switched, self.costs, self.sent = "yellow", time.monotonic(), [], 0
        self.rng = np.random.default_rng(0)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._work, daemon=True)
        self.thread.start()

    def set(self, mode: str) -> None:
        self.mode, self.switched = mode, time.monotonic()

    def _work(self) -> None:
        due = time.monotonic()
        while not self._stop.is_set():
            t = self.sent * self.period
            q = self.q0 + 0.05 * np.sin(t) * np.array([1.0, 0.5, 0.5, 0.0, 0.0, 0.0])[:len(self.q0)]
            force = (np.full(self.n, self.vmax) if self.mode == "yellow"
                     else self.rng.uniform(0.0, 0.4 * self.vmax, self.n))
            t0 = time.perf_counter()
            self.push(t, q, force)
            self.costs.append(time.perf_counter() - t0)
            self.sent += 1
            due += self.period
            self._stop.wait(max(0.0, due - time.monotonic()))
            due = max(due, time.monotonic() - self.period)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(5)


def _viser(design, robot, port: int):
    from skinsafe.core.runtime.view_page import Page

    with contextlib.redirect_stdout(sys.stderr):  # viser's banner: not into --json
        page = Page(design, robot.model, "127.0.0.1", port, title="skinsafe bench", q0=robot.home)
    base = {"kind": "frame", "command": [0.0] * robot.model.nv, "planned": None, "retracting": False, "pool": [],
            "potential": 0.0, "speed_factor": 1.0, "flags": [], "stop": "", "board_age_ms": {}, "frames_lost": 0}

    def push(t, q, force):
        page.show({**base, "t": t, "q": q.tolist()}, force)
    return page.url, push, page.vmax, page.close


def _rerun(design, robot, port: int):
    import mujoco
    import rerun as rr

    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.runtime.view_page import point_size, skin_bodies
    from skinsafe.core.runtime.view_scale import colours, default_vmax

    kin = TaxelKinematics(robot.model, design)
    m, d = robot.model, kin.data
    vmax, size = default_vmax(design.taxels.thresholds["force"]), point_size(design)
    rec = rr.RecordingStream("skinsafe_bench")
    grpc = rr.serve_grpc(grpc_port=port + 1, recording=rec)
    rr.serve_web_viewer(web_port=port + 2, open_browser=False, connect_to=grpc)
    bodies, clouds = [], {}
    t = design.taxels
    for b, name, surf, idx in skin_bodies(m, kin):
        bodies.append(b)
        if surf is not None:
            rec.log(f"robot/{name}/mesh", rr.Mesh3D(vertex_positions=surf.vertices, triangle_indices=surf.triangles,
                                                    albedo_factor=[185, 188, 195]), static=True)
        if len(idx):
            pts = t.positions[idx] + 0.0015 * t.frames[idx, :, 2]
            rec.log(f"robot/{name}/taxels", rr.Points3D(pts, radii=size / 2), static=True)
            clouds[b] = idx

    def push(tt, q, force):
        d.qpos[:len(q)] = q
        mujoco.mj_kinematics(m, d)
        rgb = colours(force, vmax)
        rec.set_time("t", duration=tt)
        for b in bodies:
            rec.log(f"robot/{m.body(b).name}", rr.Transform3D(translation=d.xpos[b], mat3x3=d.xmat[b].reshape(3, 3)))
            if b in clouds:
                rec.log(f"robot/{m.body(b).name}/taxels", rr.Points3D.from_fields(colors=rgb[clouds[b]]))
    url = f"http://127.0.0.1:{port + 2}/?url=" + grpc.replace("+", "%2B")
    return url, push, vmax, rec.disconnect


def _measure(browser, name: str, url: str, source: Source, seconds: float, trials: int) -> dict:
    page = browser.new_page(viewport={"width": W, "height": H})
    page.add_init_script(COUNT_FRAMES)
    errors = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    t0 = time.monotonic()
    page.goto(url, timeout=120000)
    load, why = float("nan"), ""
    while not why:  # until the skin is drawn (its all-yellow first update), the page failed, or 180 s
        if yellow(page.screenshot()) >= DRAWN:
            load = time.monotonic() - t0
            break
        fatal = [e for e in errors if FATAL.search(e)]
        why = (fatal[0].splitlines()[0][:200] if fatal else
               "the skin not drawn within 180 s" if time.monotonic() - t0 > 180 else "")
        page.wait_for_timeout(100)
    source.set("cool")
    page.wait_for_timeout(2000)
    f0, c0, w0, s0, k0 = page.evaluate("window.__frames"), time.process_time(), time.monotonic(), source.sent, len(source.costs)
    page.wait_for_timeout(seconds * 1000)
    frames, cpu, wall = page.evaluate("window.__frames") - f0, time.process_time() - c0, time.monotonic() - w0
    sent, costs = source.sent - s0, np.array(source.costs[k0:]) * 1e3
    lat = []
    for _ in range(trials if not why else 0):
        source.set("cool")
        page.wait_for_timeout(1500)
        while yellow(page.screenshot()) >= COOL:
            page.wait_for_timeout(100)
        source.set("yellow")
        while yellow(page.screenshot()) < DRAWN:
            if time.monotonic() - source.switched > 60:
                raise RuntimeError(f"bench viewers: {name}: an all-yellow update never showed")
        lat.append(time.monotonic() - source.switched)
    page.close()
    nan = float("nan")
    return {"page_load_s": load, "render_fps": frames / wall if not why else 0.0, "updates_hz": sent / wall,
            "latency_ms_p50": float(np.median(lat)) * 1e3 if lat else nan,
            "latency_ms_max": float(np.max(lat)) * 1e3 if lat else nan,
            "server_ms_p50": float(np.percentile(costs, 50)), "server_ms_p99": float(np.percentile(costs, 99)),
            "server_cpu": cpu / wall, "error": why}


def rows(args) -> list[dict]:
    exe = require_chromium("bench viewers")  # before playwright is imported
    from playwright.sync_api import sync_playwright

    from skinsafe.core.bench.runtime import sample_skin
    from skinsafe.core.robot.models import build_ur5

    robot = build_ur5()
    design = sample_skin(args.taxels, 1024, robot)
    out = []
    with sync_playwright() as p:
        for k, name in enumerate(args.viewers):
            pkg = "viser" if name == "viser" else "rerun-sdk"
            try:
                ver = version(pkg)
            except PackageNotFoundError:
                out.append({"viewer": name, "taxels": design.n_taxels, "error": f"{pkg} not installed"})
                continue
            browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS + (WEBGPU_ARGS if "webgpu" in name else []))
            url, push, vmax, close = (_viser if name == "viser" else _rerun)(design, robot, args.port + 10 * k)
            source = Source(push, robot.home, design.n_taxels, vmax, args.hz)
            try:
                row = _measure(browser, name, url, source, args.seconds, args.trials)
            finally:
                source.close()
                close()
                browser.close()
            out.append({"viewer": name, "version": ver, "taxels": design.n_taxels, "hz": args.hz, **row,
                        "load_average": os.getloadavg()[0], "cpus": os.cpu_count()})
    return out
