"""`skinsafe view SOURCE`: the live view in a browser (viser), of a running `skinsafe run --view` or a record.

SOURCE is `HOST:PORT` (a view stream: `skinsafe run --view` publishes one, core/runtime/view_stream.py) or
`FILE.mcap` (a `run --record` record, or an experiment's: core/runtime/sim_record.py; read by core/runtime/
recording.py). `--tracking RESULT.json` / `--collaboration RESULT.json` run an episode of the tracking or
the collaboration experiment again into a record first (core/app/experiment_view.py). The page
(core/runtime/view_page.py) runs in this process, apart from the control loop: a live view takes the newest
tick at `--fps` and drops the rest; a record gets a timeline (slider, play, next contact). `--publish
[HOST:]PORT` also replays a record as a view stream, following the timeline (Blender's add-on attaches to it
as to a live run, or opens the record itself).
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from skinsafe.core.runtime.recording import Recording
from skinsafe.core.runtime.replay import ReplayError
from skinsafe.core.runtime.rosbag2 import is_record
from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.view_stream import DEFAULT_PORT, StreamError, ViewClient, ViewPublisher, hello


def add_arguments(p) -> None:
    p.add_argument("source", nargs="?", help="HOST:PORT of a live view stream (`skinsafe run --view`), or a record "
                   "folder (`skinsafe run --record DIR`) or FILE.mcap")
    p.add_argument("--host", default="127.0.0.1", help="address the page is served on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="the page's port (default 8080)")
    p.add_argument("--fps", type=float, default=20.0, help="page updates per second at most (live; default 20)")
    p.add_argument("--vmax", type=float, help="top of the colour scale, N (default: twice the largest threshold)")
    p.add_argument("--map", help="the taxel map (default: the one the source names)")
    p.add_argument("--publish", metavar="[HOST:]PORT", help="record: also publish it as a view stream (for Blender), "
                   "following the timeline")
    p.add_argument("--seconds", type=float, help="serve this long, then exit (default: until Ctrl-C)")
    g = p.add_argument_group("an experiment's episode (run again into a record, then viewed)")
    g.add_argument("--tracking", metavar="RESULT.json", help="a `skinsafe experiment tracking` result (tracking.json)")
    g.add_argument("--method", default="vanilla", help="--tracking: vanilla | tdm | tdm2 (default vanilla)")
    g.add_argument("--seed", type=int, default=None, help="--tracking: the seed (default: the result's first)")
    g.add_argument("--episode", type=int, default=0, help="--tracking: the episode (default 0)")
    g.add_argument("--collaboration", metavar="RESULT.json", help="a `skinsafe experiment collaboration` result "
                   "(collaboration.json, its collaboration_skin.json beside it): a nominal episode")
    g.add_argument("--scenario", default="delivery", help="--collaboration: delivery | clamp | person (default delivery)")
    g.add_argument("--stack", default="full+pfl", help="--collaboration: none | retraction | full | full+pfl "
                   "(default full+pfl)")
    g.add_argument("--record", metavar="FILE.mcap", help="--tracking/--collaboration: where to write the record "
                   "(default: beside RESULT.json); `skinsafe view FILE.mcap` opens it again")
    p.add_argument("--until-ended", action="store_true", help="live: exit when the stream ends (as the page "
                   "`run --view` starts does, so it never outlives its run)")


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
    """The page of a live stream. While no browser has the page open it is off the stream (nothing is sent, encoded
    or, in `run --view`, copied by the loop for it) and attaches again when one opens it."""
    from skinsafe.core.runtime.view_page import Page

    where = _endpoint(args.source)
    client = ViewClient(*where)
    h = client.hello
    client.close()  # attached again when a browser opens the page
    client = None
    design, robot = _load_design(h["map"], args.map)
    if design.n_taxels != h["n_taxels"]:
        raise StreamError(f"the stream has {h['n_taxels']} taxels, the map {design.n_taxels}; give the run's map with --map")
    page = Page(design, robot.model, args.host, args.port, args.vmax, "skinsafe live", h["boards"], q0=robot.home,
                board_period_s=h.get("board_period_s", 0.0))
    print(f"skinsafe view: live from {args.source} ({h['n_taxels']} taxels) at {page.url}", flush=True)
    parent = os.getppid()
    try:
        while not stop.is_set() and not (args.until_ended and os.getppid() != parent):
            if not page.watched():  # nobody looking: off the stream (the machine is the robot's)
                if client is not None:
                    client.close()
                    client = None
            else:
                if client is None:
                    client = _reattach(where, h)
                    if client is None:
                        break
                latest = client.poll()
                if latest is not None:
                    page.show(*latest, live=True)
                if client.closed:
                    break
            stop.wait(1.0 / args.fps)
        if not stop.is_set():
            print("skinsafe view: the stream ended (the run stopped)", file=sys.stderr)
            if not args.until_ended:
                stop.wait()  # the page keeps the last tick until Ctrl-C / --seconds
    finally:
        if client is not None:
            client.close()
        page.close()
    return 0


def _reattach(where: tuple[str, int], first: dict) -> ViewClient | None:
    """The stream at `where` again, if it is still the one that said `first` (None: it ended)."""
    try:
        client = ViewClient(*where)
    except StreamError:
        return None
    if client.hello != first:  # another run on that port since: not this page's
        client.close()
        return None
    return client


def serve_record(args, stop: threading.Event) -> int:
    from skinsafe.core.runtime.view_page import Page

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
        tap.publish(rec.tick(state["i"]))

    step = float(cfg.get("period_s") or np.median(np.diff(rec.t)) if len(rec.t) > 1 else 0.01)
    page = Page(design, robot.model, args.host, args.port, args.vmax, f"skinsafe {Path(args.source).name}",
                {b.uid: b.name for b in design.boards}, (float(rec.t[0]), float(rec.t[-1]), step), on_time,
                rec.next_contact, cfg.get("obstacles", ()), rec.q[0], cfg.get("board_period_s", 0.0))
    page.plot_series(rec.t, rec.retracting, rec.speed_factor, rec.potential)
    on_time(rec.t[0])
    pub = None
    if args.publish:
        host, port = _endpoint(args.publish)
        pub = ViewPublisher(tap.latest, hello(design.n_taxels, design.taxels.ids, cfg["joint_names"],
                                              {b.uid: b.name for b in design.boards}, cfg["map"],
                                              cfg.get("map_sha256", ""), cfg.get("period_s", 0.0), "record",
                                              cfg.get("board_period_s", 0.0)),
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


def _tracking_record(args) -> str:
    from skinsafe.core.app.experiment_view import record_tracking

    if args.seed is None:
        seeds = json.loads(Path(args.tracking).read_text()).get("runs", {}).get(args.method, {})
        args.seed = min((int(k) for k in seeds), default=0)
    out = Path(args.record or Path(args.tracking).with_name(f"tracking_{args.method}_s{args.seed}_e{args.episode}.mcap"))
    print(f"skinsafe view: running {args.method} seed {args.seed} episode {args.episode} of {args.tracking} again "
          f"into {out}", flush=True)
    r = record_tracking(args.tracking, out, args.method, args.seed, args.episode)
    same = "as" if r["contacts"] == r["contacts_in_result"] else "NOT as"
    print(f"skinsafe view: {r['ticks']} ticks, {r['contacts']} contact ticks ({same} in the result: "
          f"{r['contacts_in_result']})", flush=True)
    return str(out)


def _collaboration_record(args) -> str:
    from skinsafe.core.app.experiment_view import contact_summary, record_collaboration

    out = Path(args.record or Path(args.collaboration).with_name(f"collaboration_{args.scenario}_{args.stack}.mcap"))
    print(f"skinsafe view: running the nominal {args.scenario}/{args.stack} episode of {args.collaboration} again "
          f"into {out}", flush=True)
    r = record_collaboration(args.collaboration, out, args.scenario, args.stack)
    print(f"skinsafe view: {r['ticks']} ticks; contacts (peak, ratio to the ISO/TS 15066 limit): "
          f"{contact_summary(r['contacts'])}", flush=True)
    print(f"skinsafe view: the result's {args.scenario}/{args.stack} contacts: {contact_summary(r['contacts_in_result'])}"
          + (" (the same episode)" if r["same"] else " -- NOT the same: the code, the skin or the machine differs "
             "from the run that wrote the result"), flush=True)
    return str(out)


def _check(args) -> None:
    """The numbers, before anything is served (ValueError: exit 2 with the message)."""
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port {args.port}: give 1..65535, or 0 for any free port")
    if not (np.isfinite(args.fps) and 0 < args.fps <= 1000):
        raise ValueError(f"--fps {args.fps}: give page updates per second in (0, 1000]")
    for name, x in (("--vmax", args.vmax), ("--seconds", args.seconds)):
        if x is not None and not (np.isfinite(x) and x > 0):
            raise ValueError(f"{name} {x}: give a finite number > 0")
    for name, x in (("--seed", args.seed), ("--episode", args.episode)):
        if x is not None and x < 0:
            raise ValueError(f"{name} {x}: give a number >= 0")


def run(args) -> int:
    stop = threading.Event()
    try:
        _check(args)
    except ValueError as e:
        print(f"skinsafe view: {e}", file=sys.stderr)
        return 2
    if args.seconds is not None:
        timer = threading.Timer(args.seconds, stop.set)
        timer.daemon = True
        timer.start()
    try:
        if args.tracking and args.collaboration:
            raise ValueError("give --tracking or --collaboration, not both")
        if args.tracking:
            args.source = _tracking_record(args)
        if args.collaboration:
            args.source = _collaboration_record(args)
        if not args.source:
            raise ValueError("give HOST:PORT, a record FILE.mcap, --tracking RESULT.json or --collaboration RESULT.json")
        if is_record(args.source):
            return serve_record(args, stop)
        return serve_live(args, stop)
    except (StreamError, ReplayError, ValueError, OSError) as e:
        print(f"skinsafe view: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        stop.set()
        return 130
