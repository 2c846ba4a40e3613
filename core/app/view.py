"""`skinsafe view SOURCE`: the live view in a browser (viser), of a running `skinsafe run --view` or a record.

SOURCE is `HOST:PORT` (a view stream: `skinsafe run --view` publishes one, core/runtime/view_stream.py) or
`FILE.mcap` (a `run --record` record, or an experiment's: core/runtime/sim_record.py). The page (core/app/
view_page.py) runs in this process, apart from the control loop: a live view takes the newest tick at
`--fps` and drops the rest; a record gets a timeline (slider, play, next contact). `--publish [HOST:]PORT`
also replays a record as a view stream, so Blender's add-on can attach to it as to a live run.
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np

from skinsafe.core.runtime.replay import ReplayError, read_record
from skinsafe.core.runtime.tap import Frame, Tap
from skinsafe.core.runtime.view_stream import DEFAULT_PORT, StreamError, ViewClient, ViewPublisher, hello


def add_arguments(p) -> None:
    p.add_argument("source", help="HOST:PORT of a live view stream (`skinsafe run --view`), or a record FILE.mcap")
    p.add_argument("--host", default="127.0.0.1", help="address the page is served on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="the page's port (default 8080)")
    p.add_argument("--fps", type=float, default=20.0, help="page updates per second at most (live; default 20)")
    p.add_argument("--vmax", type=float, help="top of the colour scale, N (default: twice the largest threshold)")
    p.add_argument("--map", help="the taxel map (default: the one the source names)")
    p.add_argument("--publish", metavar="[HOST:]PORT", help="record: also publish it as a view stream (for Blender), "
                   "following the timeline")
    p.add_argument("--seconds", type=float, help="serve this long, then exit (default: until Ctrl-C)")


class Recording:
    """A record's ticks as arrays (time on the robot's clock) and the view-stream frame of any tick."""

    def __init__(self, path: str | Path):
        self.config, messages = read_record(path, diagnostics=True)
        t, q, cmd, planned, force_at, layers, diag = [], [], [], [], [], [], []
        forces, cur = [], {}
        for topic, msg in messages:
            if topic == "/joint_states":
                cur["q"] = np.asarray(msg.position, float)
            elif topic == "/skinsafe/command":
                cur["command"] = np.asarray(msg.velocity, float)
            elif topic == "/skinsafe/planned":
                cur["planned"] = np.asarray(msg.velocity, float)
            elif topic == "/skinsafe/taxels":
                forces.append(msg.astype(np.float32))
            elif topic == "/skinsafe/layers":
                cur["layers"] = msg
            elif topic == "/skinsafe/tick":
                t.append(msg[0])
                q.append(cur.get("q"))
                cmd.append(cur.get("command"))
                planned.append(cur.get("planned"))
                force_at.append(len(forces) - 1)
                layers.append(cur.pop("layers", None))
            elif topic == "/diagnostics":
                diag.append((t[-1] if t else 0.0, _diagnostics(msg)))
        if not t or q[0] is None:
            raise ReplayError(f"{path}: no tick recorded (the robot never moved)")
        self.t = np.asarray(t)
        self.q, self.command = np.array(q), np.array(cmd)
        self.planned = planned
        self.forces = np.array(forces) if forces else np.zeros((1, 0), np.float32)
        self.force_at = np.asarray(force_at)
        none = np.array([0.0, 1.0, 0.0, 0.0])
        self.layers = [x if x is not None else none for x in layers]
        self.potential = np.array([x[0] for x in self.layers])
        self.speed_factor = np.array([x[1] for x in self.layers])
        self.retracting = np.array([x[2] for x in self.layers])
        self.diag_t = np.array([d[0] for d in diag])
        self.diag = [d[1] for d in diag]
        self.stop = next((d["skinsafe/watchdog"]["message"] for _, d in diag[::-1] if "skinsafe/watchdog" in d), "")
        peak = np.array([np.nanmax(f) if f.size else 0.0 for f in self.forces])
        self.peak = np.where(self.force_at >= 0, peak[np.maximum(self.force_at, 0)], 0.0)

    def index(self, t: float) -> int:
        """The tick nearest to time t."""
        i = int(np.clip(np.searchsorted(self.t, t), 1, max(1, len(self.t) - 1)))
        return i - 1 if len(self.t) < 2 or t - self.t[i - 1] <= self.t[i] - t else i

    def frame(self, i: int) -> tuple[dict, np.ndarray]:
        """Tick i in the view stream's frame format (header, forces)."""
        k = self.force_at[i]
        force = self.forces[k].astype(float) if k >= 0 else np.full(self.forces.shape[1], np.nan)
        lay = self.layers[i]
        d = self.diag[max(0, int(np.searchsorted(self.diag_t, self.t[i], side="right")) - 1)] if self.diag else {}
        layers = d.get("skinsafe/layers", {}).get("values", {})
        skin = d.get("skinsafe/skin", {}).get("values", {})
        ages = {k.split()[1]: float(v) for k, v in skin.items() if k.startswith("board ")}
        last = i == len(self.t) - 1
        h = {"kind": "frame", "seq": i + 1, "t": float(self.t[i]), "q": self.q[i].tolist(),
             "command": self.command[i].tolist(), "planned": None if self.planned[i] is None else self.planned[i].tolist(),
             "retracting": bool(lay[2]), "pool": [int(x) for x in lay[4:]], "potential": float(lay[0]),
             "speed_factor": float(lay[1]), "flags": [f for f in layers.get("flags", "").split(",") if f],
             "stop": self.stop if last else "", "board_age_ms": {str(int(u, 16)): a for u, a in ages.items()},
             "frames_lost": int(skin.get("frames_lost", 0))}
        return h, force

    def next_contact(self, t: float) -> float | None:
        """The time of the largest reading of the next retraction after `t` (None: no more)."""
        i = self.index(t)
        on = np.flatnonzero((self.retracting[i + 1:] > 0) & (self.retracting[i:-1] == 0)) + i + 1 if i + 1 < len(
            self.t) else np.zeros(0, int)
        if not len(on):
            return None
        start = int(on[0])
        end = start + int(np.argmax(self.retracting[start:] == 0)) if (self.retracting[start:] == 0).any() else len(self.t)
        return float(self.t[start + int(np.argmax(self.peak[start:end]))])

    def tap_frame(self, i: int) -> Frame:
        """Tick i as the runtime's tap frame (for `--publish`)."""
        h, force = self.frame(i)
        return Frame(h["t"], self.q[i], force, self.command[i], h["retracting"], len(h["pool"]), tuple(h["flags"]),
                     h["stop"], self.planned[i], np.array(h["pool"]), h["potential"], h["speed_factor"],
                     {int(k): v / 1e3 for k, v in h["board_age_ms"].items()}, h["frames_lost"])


def _diagnostics(msg) -> dict:
    return {s.name: {"level": int(s.level), "message": s.message, "values": {kv.key: kv.value for kv in s.values}}
            for s in msg.status}


def _load_design(map_path: str, override: str | None):
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.skin.taxel_map import load

    mp = Path(override or map_path)
    try:
        design = load(mp)
    except OSError as e:
        raise StreamError(f"the taxel map {mp} cannot be read ({e.strerror or e}); give it with --map") from None
    robot = load_robot(design.robot, base_dir=mp.parent)
    return load(mp, robot.body_names), robot


def _endpoint(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    try:
        return host or default_host, int(port)
    except ValueError:
        raise StreamError(f"{text!r}: give HOST:PORT (e.g. 127.0.0.1:{DEFAULT_PORT}) or a record FILE.mcap") from None


def serve_live(args, stop: threading.Event) -> int:
    from skinsafe.core.app.view_page import Page

    client = ViewClient(*_endpoint(args.source))
    h = client.hello
    design, robot = _load_design(h["map"], args.map)
    if design.n_taxels != h["n_taxels"]:
        raise StreamError(f"the stream has {h['n_taxels']} taxels, the map {design.n_taxels}; give the run's map with --map")
    page = Page(design, robot.model, args.host, args.port, args.vmax, "skinsafe live", h["boards"], q0=robot.home)
    print(f"skinsafe view: live from {args.source} ({h['n_taxels']} taxels) at {page.url}", flush=True)
    try:
        while not stop.is_set() and not client.closed:
            newest = client.poll()
            if newest is not None:
                page.show(*newest, live=True)
            stop.wait(1.0 / args.fps)
        if client.closed:
            print("skinsafe view: the stream ended (the run stopped)", file=sys.stderr)
            stop.wait()  # the page keeps the last tick until Ctrl-C / --seconds
    finally:
        client.close()
        page.close()
    return 0


def serve_record(args, stop: threading.Event) -> int:
    from skinsafe.core.app.view_page import Page

    rec = Recording(args.source)
    cfg = rec.config
    design, robot = _load_design(cfg["map"], args.map)
    if design.n_taxels != rec.forces.shape[1]:
        raise StreamError(f"{args.source}: {rec.forces.shape[1]} taxels recorded, the map {design.n_taxels}; give "
                          "the run's map with --map")
    state = {"i": 0}
    tap = Tap()

    def on_time(t):
        state["i"] = rec.index(t)
        page.show(*rec.frame(state["i"]))
        tap.publish(rec.tap_frame(state["i"]))

    step = float(cfg.get("period_s") or np.median(np.diff(rec.t)) if len(rec.t) > 1 else 0.01)
    page = Page(design, robot.model, args.host, args.port, args.vmax, f"skinsafe {Path(args.source).name}",
                {b.uid: b.name for b in design.boards}, (float(rec.t[0]), float(rec.t[-1]), step), on_time,
                rec.next_contact, cfg.get("obstacles", ()), rec.q[0])
    page.plot_series(rec.t, rec.retracting, rec.speed_factor, rec.potential)
    on_time(rec.t[0])
    pub = None
    if args.publish:
        host, port = _endpoint(args.publish)
        pub = ViewPublisher(tap.latest, hello(design.n_taxels, design.taxels.ids, cfg["joint_names"],
                                              {b.uid: b.name for b in design.boards}, cfg["map"],
                                              cfg.get("map_sha256", ""), cfg.get("period_s", 0.0), "record"),
                            host, port)
        print(f"skinsafe view: publishing the record's timeline at {pub.address[0]}:{pub.address[1]}", flush=True)
    print(f"skinsafe view: {args.source}: {len(rec.t)} ticks, {rec.t[-1] - rec.t[0]:.2f} s, {design.n_taxels} taxels "
          f"at {page.url}", flush=True)
    try:
        last = time.monotonic()
        while not stop.wait(0.05):
            now = time.monotonic()
            if page.slider is not None and page.playing:
                t = float(page.slider.value) + (now - last)
                if t >= rec.t[-1]:
                    t, page.playing = float(rec.t[-1]), False
                page.goto(t)
            last = now
    finally:
        if pub is not None:
            pub.close()
        page.close()
    return 0


def run(args) -> int:
    stop = threading.Event()
    if args.seconds is not None:
        timer = threading.Timer(args.seconds, stop.set)
        timer.daemon = True
        timer.start()
    try:
        if args.source.endswith(".mcap"):
            return serve_record(args, stop)
        return serve_live(args, stop)
    except (StreamError, ReplayError, ValueError, OSError) as e:
        print(f"skinsafe view: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        stop.set()
        return 130
