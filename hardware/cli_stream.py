"""`skinsafe stream skin.json --port PORT | --all`: readings mapped to taxels, danger events, lost/corrupt counts.

Ends with one line per board (received, lost, corrupt, resynced of the frames it sent; replayed
frames dropped and other uids' frames refused, where any) and a summary. A board whose link is lost
ends the stream: the others are stopped. Exit codes: 0 streamed and stopped; 1 a board was refused,
failed to start (every board a start was sent to is stopped), lost its link, did not confirm its
stop, or was not found; 2 bad input; 130 Ctrl-C; 143 SIGTERM.
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

from skinsafe.core.safety.events import danger_events
from skinsafe.core.skin.model import DesignError
from skinsafe.core.skin.taxel_map import load
from skinsafe.hardware.cli_deploy import add_port_arguments, check_link_options, find_ports
from skinsafe.hardware.client import BoardError
from skinsafe.hardware.interrupt import for_command
from skinsafe.hardware.protocol import stream_frame_bytes
from skinsafe.hardware.stream import SkinStream, StreamUpdate, achievable_hz


def add_arguments(p) -> None:
    add_port_arguments(p)
    p.add_argument("--rate", type=int, default=100, help="frames per second per board (1..65535; warned when "
                   "more than the link carries at --baud)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--no-verify", action="store_true", help="stream even if a board runs another config")
    p.add_argument("--restart", action="store_true",
                   help="stop a board that is already streaming and start it again (default: refuse it)")


class DangerPrinter:
    """Prints taxels entering danger (core.events.danger_events on each poll's peak), each board's first
    fault of each kind, and a status line per second."""

    def __init__(self, design, out=None):
        self.ids, self.thresholds, self.out = design.taxels.ids, design.taxels.thresholds, out or sys.stdout
        self.active = np.zeros(design.n_taxels, bool)
        self.t0 = self.last = time.monotonic()
        self.events = 0
        self.named: set[tuple[int, str]] = set()

    def __call__(self, u: StreamUpdate) -> None:
        for f in u.faults:
            if (f.board_id, f.kind) not in self.named:
                self.named.add((f.board_id, f.kind))
                print(f"{u.t - self.t0:8.3f} s  FAULT {f}" + ("" if f.kind == "link lost" else " (more are counted in the last lines)"),
                      file=self.out, flush=True)
        d = danger_events({"force": u.peak}, {"force": self.thresholds["force"]})
        new = d & ~self.active
        self.active = d | (self.active & np.isnan(u.peak))  # taxels without a new frame keep their state
        if new.any():
            self.events += int(new.sum())
            ids = self.ids[new]
            print(f"{u.t - self.t0:8.3f} s  DANGER {len(ids)} taxels {ids[:8].tolist()}"
                  f"{' ...' if len(ids) > 8 else ''} (max {np.nanmax(u.peak[new]):.1f} N)", file=self.out)
        if u.t - self.last >= 1.0:
            self.last = u.t
            print(f"{u.t - self.t0:8.3f} s  frames {sum(v[0] for v in u.per_board.values())}  lost {u.lost}  "
                  f"corrupt {u.corrupt}  in danger {int(self.active.sum())}", file=self.out, flush=True)


def run(args) -> int:
    with for_command() as stop:
        try:
            check_link_options(args)
            if not 1 <= args.rate <= 65535:
                raise DesignError(f"--rate {args.rate}: give frames per second per board, 1..65535")
            if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
                raise DesignError(f"--seconds {args.seconds}: give a positive duration")
            design = load(args.map)
            ports, missing, notes, problems = find_ports(design, args, stop)
        except DesignError as e:
            print(f"skinsafe stream: {e}", file=sys.stderr)
            return 2
        for msg in [f"note: {m}" for m in notes] + [f"problem: {m}" for m in problems] + [r.line() for r in missing]:
            print(msg, file=sys.stderr)
        if stop.requested:
            print(f"skinsafe stream: interrupted by {stop.name} before streaming", file=sys.stderr)
            return stop.exit_code
        if not ports:
            print("skinsafe stream: no board of the map was found", file=sys.stderr)
            return 1
        for b in design.boards:
            top = achievable_hz(args.baud, b.capacity)
            if b.id in ports and args.rate > top:
                print(f"warning: board {b.id} '{b.name}': a frame of {b.capacity} channels is "
                      f"{stream_frame_bytes(b.capacity)} bytes; at {args.baud} baud the link carries at most "
                      f"{int(top)} frames/s, asked {args.rate}", file=sys.stderr)
        printer = DangerPrinter(design)
        try:
            stream = SkinStream(design, ports, args.rate, verify=not args.no_verify, restart=args.restart,
                                cancel=stop, baud=args.baud, timeout=args.timeout, retries=args.retries)
        except BoardError as e:  # one line per board refused
            print("\n".join(f"skinsafe stream: {line}" for line in str(e).splitlines()), file=sys.stderr)
            return stop.exit_code if stop.requested else 1
        try:
            stream.start()
            print(f"skinsafe stream: {len(stream.boards)} boards streaming at {args.rate} Hz (Ctrl-C stops cleanly)",
                  file=sys.stderr, flush=True)

            def on_update(u: StreamUpdate) -> bool:
                printer(u)
                return not stop.requested and not any(f.kind == "link lost" for f in u.faults)

            stream.run(on_update, args.seconds)
            failed = "; ".join(s.lost_link for s in stream.boards if s.lost_link)
        except BoardError as e:
            failed = str(e)
        finally:
            unconfirmed = stream.stop()
            stream.close()
    by_id = {b.id: b for b in design.boards}
    for s in stream.boards:
        st, b = s.stats(), by_id[s.board_id]
        if s.stopped:
            state = "stopped"
        elif s.lost_link:
            state = "link lost"
        elif s.board_id in unconfirmed:
            state = "stop not confirmed: " + unconfirmed[s.board_id]
        else:
            state = "not started"
        extra = (f"; dropped {st.replayed} replayed or out-of-order frames" if st.replayed else "") + "".join(
            f"; refused {n} frames from uid {uid:#x}" for uid, n in sorted(s.client.foreign.items()))
        print(f"board {b.id} '{b.name}' uid {b.uid:#x} on {s.client.port}: {state}; received {st.received}, "
              f"lost {st.lost}, corrupt {st.corrupt}, resynced {st.resynced} of {s.sent} frames sent{extra}")
    totals = [sum(s.stats()[k] for s in stream.boards) for k in range(6)]
    dropped = f"; {totals[4]} replayed dropped, {totals[5]} foreign refused" if totals[4] or totals[5] else ""
    print(f"done: {totals[0]} frames, {totals[1]} lost, {totals[2]} corrupt, {totals[3]} resynced, "
          f"{printer.events} danger events{dropped}" + (f"; interrupted by {stop.name}" if stop.requested else ""))
    if failed:
        print(f"skinsafe stream: {failed}; the other boards were stopped", file=sys.stderr)
    if stop.requested:
        return stop.exit_code
    return 1 if failed or unconfirmed or missing or problems else 0
