"""`skinsafe bench runtime --view alternating`: the view's load on the loop, compared inside one run.

Runs of one mode differ from each other by more than 5% at p99 on a shared 2-vCPU machine (where the host
puts the virtual CPUs, what else it runs that minute), so a comparison of runs with the view against runs
without it cannot resolve 5%. Here each run has the view attached throughout (`run --view` and a headless
Chromium drawing its page, on any core; `alternating-pinned`: off the loop's core; `alternating-remote`: the page
open on another computer, core/bench/remote_viewer.py), and the view's processes (the stream's publisher, the
page's server, every Chromium process or the remote viewer) are paused (SIGSTOP) and resumed (SIGCONT) every
`block` seconds: the ticks while the view worked are compared with the ticks of the same run while it was
paused, block against the block next to it (with `--block` equal to `--sweep`, each block holds one whole
sweep of the arm into the post and back: the two blocks of a pair did the same work). The loop's own side of
the view, its tap's copy into shared memory 30 times a second, is in the comparison too: the loop copies only
while the publisher reads (core/runtime/view_share.py), so it stops within `SharedFrames.LEASE_S` of a pause
(`bench runtime --tap` measures the copy alone).
"""
from __future__ import annotations

import itertools
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np

from skinsafe.core.timing import pct, pooled_change_ci95

REMOTE_VIEWER = "skinsafe.core.bench.remote_viewer"  # `python -m` it: a page open on another computer
VIEW_MODULES = ("skinsafe.core.runtime.view_share", REMOTE_VIEWER)  # the publisher, a remote page
PAGE_COMMAND = "view"  # `python -m <skinsafe's CLI> view`: the page's process (`run --view` starts it)


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(d.name))
    return kids


def view_processes(root: int, browser_exe: str | None) -> list[int]:
    """Descendants of `root` that are the view: the publisher, the page's server, the browser's processes (of
    `browser_exe`) or the remote viewer."""
    kids, out, todo = _children(), [], [root]
    while todo:
        for pid in kids.get(todo.pop(), []):
            todo.append(pid)
            try:
                argv = (Path("/proc") / str(pid) / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            args = [a.decode(errors="replace") for a in argv]
            program = os.path.basename(args[0].split(" ")[0])  # Chromium's helpers rewrite argv into one string
            if (browser_exe and program == os.path.basename(browser_exe)) or any(m in args for m in VIEW_MODULES) or \
                    (len(args) > 3 and args[1] == "-m" and args[3] == PAGE_COMMAND):
                out.append(pid)
    return out


def cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system) process `pid` has used so far (None: gone)."""
    try:
        f = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


class Pauser:
    """Pauses and resumes the view's processes every `block` s from `start()` until `stop()`; `switches`: the
    (time.monotonic, paused) of each switch, the first a resume; `cpu_s`: the CPU seconds they used meanwhile."""

    def __init__(self, root: int, browser_exe: str | None, block: float):
        self.root, self.exe, self.block = root, browser_exe, block
        self.switches: list[tuple[float, bool]] = []
        self._cpu: dict[int, tuple[float, float]] = {}  # pid: (CPU seconds when first seen, when last seen)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def cpu_s(self) -> float:
        return sum(last - first for first, last in self._cpu.values())

    def _signal(self, sig) -> None:
        for pid in view_processes(self.root, self.exe):
            used = cpu_seconds(pid)
            if used is not None:
                self._cpu[pid] = (self._cpu.get(pid, (used, used))[0], used)
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass

    def _work(self) -> None:
        paused, start = False, time.monotonic()
        for k in itertools.count(1):
            self._signal(signal.SIGSTOP if paused else signal.SIGCONT)
            self.switches.append((time.monotonic(), paused))
            if self._stop.wait(max(0.0, start + k * self.block - time.monotonic())):  # on a fixed grid: no drift
                break
            paused = not paused
        self._signal(signal.SIGCONT)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


def blocks(run: dict, switches: list[tuple[float, bool]]) -> list[tuple[bool, dict[str, np.ndarray]]]:
    """The run's samples in the blocks between switches: (paused, {"period", "latency", "latency_tick"} in ms)
    per whole block, in order (a block the run did not span from start to end is left out)."""
    period = np.asarray(run["period_ms_all"], float)
    start = run["start_mono"] + np.concatenate(([0.0], np.cumsum(period) / 1e3))  # tick k's start
    at = np.asarray(run["latency_tick_all"], int)
    lat = np.asarray(run["latency_ms_all"], float)
    tick_part = lat - np.asarray(run["latency_wait_ms_all"], float)
    out = []
    for (t0, paused), (t1, _) in zip(switches, switches[1:]):
        if t0 < start[0] or t1 > start[-1]:
            continue
        k0, k1 = np.searchsorted(start, [t0, t1])  # the ticks that began inside the block
        inside = (at >= k0) & (at < k1)
        out.append((paused, {"period": period[max(k0 - 1, 0):k1 - 1], "latency": lat[inside],
                             "latency_tick": tick_part[inside]}))
    return out


def compare(pairs: list[tuple[dict, dict]], names, draws: int = 2000, seed: int = 0) -> dict:
    """The view's change per figure at p50 and p99: pooled over the blocks while it worked against those while it
    was paused, `*_p50_vs_paused` / `*_p99_vs_paused`, with a 95% interval over the pairs of neighbouring blocks
    resampled (`_ci95`)."""
    out = {"blocks": 2 * len(pairs)}
    idx = np.random.default_rng(seed).integers(0, len(pairs), (draws, len(pairs)))
    for name in names:
        on = [w[name] for w, _ in pairs]
        off = [p[name] for _, p in pairs]
        for q in (50, 99):
            work, rest = pct(np.concatenate(on), q), pct(np.concatenate(off), q)
            out[f"{name}_ms_p{q}_working"], out[f"{name}_ms_p{q}_paused"] = work, rest
            out[f"{name}_p{q}_vs_paused"] = work / rest - 1
            out[f"{name}_p{q}_vs_paused_ci95"] = pooled_change_ci95(on, off, idx, q)
        out[f"{name}_samples"] = int(sum(map(len, on)) + sum(map(len, off)))
    return out


def pair_blocks(runs: list[tuple[dict, list]]) -> list[tuple[dict, dict]]:
    """(working, paused) pairs of neighbouring blocks from every run: each working block with the paused one after it."""
    pairs = []
    for run, switches in runs:
        b, i = blocks(run, switches), 0
        while i + 1 < len(b):
            if not b[i][0] and b[i + 1][0]:
                pairs.append((b[i][1], b[i + 1][1]))
                i += 1
            i += 1
    return pairs
