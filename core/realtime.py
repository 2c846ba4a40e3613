"""The host's real-time settings for a control loop: scheduling, cores, idle states, thread counts.

`skinsafe run` asks for real-time priority (`realtime`), raises the loop's thread above what it started
and gives it the first core while the robot moves (`loop_priority`), keeps the emulated boards below the
host's reader (`below_host`) and the view's processes on the normal scheduler (`background`), and keeps
numpy's BLAS (and torch) on one thread (`one_thread`, `single_thread_blas`: experiments use it too, so
that their numbers do not depend on thread counts). A leaf of the package: the standard library only
(import-linter: the layer beside core/timing.py, which keeps benchmark timing alone)."""
from __future__ import annotations

import contextlib
import ctypes
import os
import resource
import sys
import time

RT_PRIORITY = 10  # the run's process and what it starts (the boards' reader, the emulator)
LOOP_PRIORITY = RT_PRIORITY + 1  # the loop's thread while the robot moves: above everything it started
EMULATOR_PRIORITY = RT_PRIORITY - 1  # emulated boards: below the host's reader and loop


def realtime(mode: str) -> str:
    """Real-time priority (SCHED_FIFO `RT_PRIORITY`) for this process and what it starts, where allowed
    (`mode` auto | off); says which it got."""
    if mode == "off" or not hasattr(os, "sched_setscheduler"):
        return "normal priority"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
    except (PermissionError, OSError):
        return "normal priority (real-time not allowed here)"
    return f"real-time priority SCHED_FIFO {RT_PRIORITY}"


def is_realtime() -> bool:
    """Whether this process runs at real-time priority now (what it got, not what it asked for)."""
    return hasattr(os, "sched_getscheduler") and os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)


def below_host(pid: int) -> None:
    """The emulated boards stand for hardware outside this computer: at real-time priority (if this process has
    it) they run below the boards' reader and the loop, never in their way (every thread of process `pid`)."""
    if os.sched_getscheduler(0) == os.SCHED_FIFO:
        each_thread(pid, os.sched_setscheduler, os.SCHED_FIFO, os.sched_param(EMULATOR_PRIORITY))


@contextlib.contextmanager
def loop_priority(rt: str):
    """While the robot moves: the loop's thread (only it: Linux schedules threads) above the reader and emulator
    processes, so a tick is never queued behind their frames, as a robot controller's thread is; with two cores
    or more, the loop keeps the first of them and the processes it started move to the others; idle cores stay
    awake (`cpus_awake`). Restored after (an in-process caller runs again). `rt`: what `realtime` said."""
    if not rt.startswith("real-time"):
        yield
        return
    cpus, policy, param = os.sched_getaffinity(0), os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(LOOP_PRIORITY))
    if len(cpus) >= 2:
        loop, rest = loop_cores(cpus)
        os.sched_setaffinity(0, loop)
        for pid in children():
            each_thread(pid, os.sched_setaffinity, rest)
    awake = cpus_awake()
    try:
        yield
    finally:
        if awake is not None:
            os.close(awake)
        os.sched_setscheduler(0, policy, param)
        os.sched_setaffinity(0, cpus)


def host_stalls(seconds: float, threshold_s: float = 1e-4, window_s: float = 0.2) -> dict:
    """What this host takes from a thread that never waits: the calling thread at the loop's priority (where
    allowed) on the loop's core reads the clock in a tight loop for `seconds` (in windows of `window_s` with a
    quarter of that asleep between: under the kernel's real-time throttling, which would pause it itself); every gap
    over `threshold_s` between two reads is time it lost. `stall_ms_max`, `stalls`, `switched_out` (its involuntary
    context switches: 0 means no other thread ran there meanwhile, so the time went below the scheduler, to
    interrupts or, on a virtual machine, the hypervisor), `realtime` (whether it ran at the loop's priority).
    Scheduling and cores restored after."""
    cpus, policy, param = os.sched_getaffinity(0), os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(LOOP_PRIORITY))
        rt = True
    except (PermissionError, OSError):
        rt = False
    os.sched_setaffinity(0, loop_cores(cpus)[0])
    clock, limit = time.perf_counter_ns, int(threshold_s * 1e9)
    worst, stalls = 0, 0
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw
    try:
        for _ in range(max(1, round(seconds / window_s))):
            last = clock()
            end = last + int(window_s * 1e9)
            while last < end:
                now = clock()
                if now - last > limit:
                    stalls += 1
                    worst = max(worst, now - last)
                last = now
            time.sleep(window_s / 4)  # a voluntary switch: not counted below
        switched = resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw - before
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, param)
        os.sched_setaffinity(0, cpus)
    return {"stall_ms_max": worst / 1e6, "stalls": stalls, "switched_out": switched, "realtime": rt}


def steal_s(cpu: int) -> float | None:
    """Seconds the hypervisor has run something else while core `cpu` of this virtual machine wanted to run (its
    `steal` in /proc/stat, since boot; 10 ms resolution); None where not reported."""
    try:
        with open("/proc/stat") as f:
            for line in f:
                if line.startswith(f"cpu{cpu} "):
                    return int(line.split()[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None
    return None


def loop_cores(cpus) -> tuple[set[int], set[int]]:
    """`cpus` split into the control loop's core (the first) and the rest, for everything else."""
    first, *rest = sorted(cpus)
    return {first}, set(rest)


def cpus_awake() -> int | None:
    """Ask the kernel to keep idle cores out of their sleep states while the file stays open (the PM QoS
    request of /dev/cpu_dma_latency at 0 us, as cyclictest and real-time robot hosts do): a core woken from a
    sleep state (on a virtual machine: the host's HLT exit) starts a tick or reads a frame tens to hundreds of
    microseconds late, and more so the quieter the machine. The open descriptor, or None where not allowed."""
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
    except OSError:
        return None
    try:
        os.write(fd, (0).to_bytes(4, sys.byteorder))
    except OSError:
        os.close(fd)
        return None
    return fd


def children() -> list[int]:
    """This process's child processes (every thread's)."""
    out = []
    for tid in _threads(os.getpid()):
        with contextlib.suppress(OSError), open(f"/proc/{os.getpid()}/task/{tid}/children") as f:
            out += [int(p) for p in f.read().split()]
    return out


def _threads(pid: int) -> list[int]:
    try:
        return [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        return []


def each_thread(pid: int, call, *args) -> None:
    """`call(tid, *args)` for every thread of process `pid` (one that ended meanwhile is skipped)."""
    for tid in _threads(pid):
        with contextlib.suppress(OSError):
            call(tid, *args)


def one_thread() -> None:
    """The loop's numerical libraries on its own thread: BLAS (and torch with --tdm) worker threads would wait for the
    cores the boards' reader and the emulator run on, and a tick's small products with them."""
    single_thread_blas()
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def background(niceness: int = 10) -> None:
    """In the view's processes before they start: the normal scheduler (not the run's real-time one, which a
    child inherits: a page at SCHED_FIFO starved the emulated boards, stopped as silent) at nice `niceness`."""
    if hasattr(os, "sched_setscheduler"):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.nice(niceness)


def single_thread_blas() -> bool:
    """Pin numpy's OpenBLAS to one thread (for control ticks of single-row products: on a busy
    machine its worker threads make a 0.3 ms tick take 15 ms). True if a BLAS was found."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower() and line.strip().endswith(".so")
                     or "openblas" in line.lower() and ".so" in line.split()[-1]}
    except OSError:
        return False
    done = False
    for path in paths:
        lib = ctypes.CDLL(path)
        for name in ("openblas_set_num_threads64_", "openblas_set_num_threads", "scipy_openblas_set_num_threads64_"):
            if hasattr(lib, name):
                getattr(lib, name)(1)
                done = True
    return done
