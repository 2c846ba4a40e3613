"""Test set-up shared by all suites.

bpy is imported first: pymeshlab and bpy both bundle Embree, and bpy fails to import after pymeshlab.
"""
import contextlib
from pathlib import Path

import bpy  # noqa: F401  (must precede any pymeshlab import)
import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """`--dist loadgroup` (a worker's `config.option.loadgroup`): a test's `xdist_group` names go at the end of its
    node id, where the scheduler finds them (one worker runs a group, in order). pytest-xdist 3.8 writes them to
    `item._nodeid`, which pytest 9.2 no longer reads (its node ids are `item._id`): without this every group splits."""
    import dataclasses

    if not getattr(config.option, "loadgroup", False):
        return
    for item in items:
        names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                        for m in item.iter_markers("xdist_group")})
        if names and hasattr(item, "_id") and item.nodeid.rfind("@") <= item.nodeid.rfind("]"):  # not grouped yet
            nid = dataclasses.replace(item._id)
            object.__setattr__(nid, "_str_cache", f"{item.nodeid}@{'_'.join(names)}")  # str(NodeId)'s own cache
            item._id = nid


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny networks: one torch thread avoids oversubscribing the shared 2-core machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# two links each, the Gen3's forearm_link among them (its name once sent poke down a UR5-only branch)
PUBLIC_LINKS = {"ur5e": ["forearm_link", "wrist_1_link"], "gen3": ["half_arm_2_link", "forearm_link"],
                "xarm7": ["link3", "link4"]}


@pytest.fixture(scope="session")
def public_skin(tmp_path_factory):
    """name -> (robot, design, taxel map path): a skin of 3x3 modules at 12 mm on two links of a
    public description (`PUBLIC_LINKS`), made once per test run; the tests that share it share its
    scenes' surface pieces too (kept in the process, never from an earlier run: see `fresh_pieces`)."""
    from skinsafe.core.app.design import design_robot
    from skinsafe.core.robot.catalog import description
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.skin.taxel_map import save

    made = {}

    def get(name: str):
        """(robot, design, map path); `get.links[name]` are the links it covers."""
        if name not in made:
            ref = description(name)
            robot = load_robot(ref)
            design = design_robot(robot, ref, {"module": {"rows": 3, "cols": 3, "pitch": 0.012},
                                               "bodies": PUBLIC_LINKS[name]})[0]
            made[name] = robot, design, save(design, tmp_path_factory.mktemp(name) / "skin.json")
        return made[name]

    get.links = PUBLIC_LINKS
    return get


@pytest.fixture(scope="session", autouse=True)
def fresh_pieces(tmp_path_factory):
    """Surface pieces and repaired meshes are kept on disk between processes (`array_cache.cache_dir`): a test run
    (its subprocesses too) starts from an empty folder, as CI's clean clone does, so it never
    passes on pieces or meshes an earlier version of the code made."""
    import os

    old = os.environ.get("SKINSAFE_PIECES")
    os.environ["SKINSAFE_PIECES"] = str(run_folder(tmp_path_factory) / "pieces")  # pieces are renamed into place
    yield
    if old is None:
        os.environ.pop("SKINSAFE_PIECES", None)
    else:
        os.environ["SKINSAFE_PIECES"] = old


def run_folder(tmp_path_factory):
    """This test run's temporary folder: under pytest-xdist the one its workers' folders are in, which they share."""
    import os

    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.fixture
def realtime_host(tmp_path_factory):
    """The machine's one real-time slot, held while a test runs the control loop (`skinsafe run`: SCHED_FIFO, the loop
    pinned to the first core, the PM QoS target held at 0, boards named silent after a set latency). Two at once, one
    per pytest-xdist worker, stall each other's ticks and frames: the `realtime` group's tests take it in turn on one
    worker; a docs block takes it only while its command that runs the loop does (`realtime_lock`)."""
    with realtime_slot(tmp_path_factory):
        yield


@pytest.fixture(scope="session")
def realtime_lock(tmp_path_factory):
    """The file whose lock (flock) is the real-time slot: a shell script holds the slot with `flock` on it."""
    return slot_file(tmp_path_factory)


@pytest.fixture(scope="session")
def realtime_turn(tmp_path_factory):
    """`realtime_host` as a context manager, for a test or fixture that runs the loop in one phase only (its other
    phases, a record's replay or decoding, run beside the real-time tests): `with realtime_turn(): ...`."""
    return lambda: realtime_slot(tmp_path_factory)


def slot_file(tmp_path_factory):
    return run_folder(tmp_path_factory) / "realtime.lock"


@contextlib.contextmanager
def realtime_slot(tmp_path_factory):
    import fcntl

    with open(slot_file(tmp_path_factory), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        yield


def _host_cpu_s() -> tuple[float, float]:
    """(busy, idle) CPU seconds of the whole machine since boot, all cores (/proc/stat; zeros where there is none)."""
    import os

    try:
        with open("/proc/stat") as f:
            ticks = [int(x) for x in f.readline().split()[1:]]
    except OSError:
        return 0.0, 0.0
    hz, idle = os.sysconf("SC_CLK_TCK"), ticks[3] + ticks[4]  # idle + iowait
    return (sum(ticks[:8]) - idle) / hz, idle / hz


def pytest_sessionstart(session):
    import time

    session.config._skinsafe_started = time.monotonic()
    session.config._skinsafe_started_epoch = time.time()
    session.config._skinsafe_host = _host_cpu_s()


def _cpu_s() -> float:
    import resource

    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                 resource.getrusage(resource.RUSAGE_CHILDREN)))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Each test's CPU seconds (this process and the children it waited for) as the user property `cpu_s` of its
    reports, with when it started and on which worker (with SKINSAFE_TEST_TIMES)."""
    import os
    import time

    if not os.environ.get("SKINSAFE_TEST_TIMES"):
        return (yield)
    item.user_properties += [("cpu_start", _cpu_s()), ("started", time.time()),
                             ("worker", os.environ.get("PYTEST_XDIST_WORKER", "main"))]
    return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):
    try:
        return (yield)
    finally:
        start = dict(item.user_properties).get("cpu_start")
        if start is not None:
            item.user_properties.append(("cpu_s", _cpu_s() - start))


def pytest_configure(config):
    """The run's hang log (SKINSAFE_HANG_LOG, inherited by xdist's workers): a test that guards a C call holding the
    interpreter lock with faulthandler (tests/runtime/test_fr3_driver.py) dumps its stacks there before it ends its
    worker, whose stderr xdist drops; the summary prints it."""
    import os
    import tempfile

    if not os.environ.get("PYTEST_XDIST_WORKER"):
        log = Path(tempfile.gettempdir()) / f"skinsafe-hangs-{os.getpid()}.txt"
        log.unlink(missing_ok=True)
        os.environ["SKINSAFE_HANG_LOG"] = str(log)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """A hung test's stacks (SKINSAFE_HANG_LOG), then the run's times (`_times_summary`)."""
    import os

    log = Path(os.environ.get("SKINSAFE_HANG_LOG", "/nonexistent"))
    if not os.environ.get("PYTEST_XDIST_WORKER") and log.is_file() and "Thread 0x" in log.read_text():
        terminalreporter.write_sep("=", f"a test hung: its stacks ({log})")
        terminalreporter.write(log.read_text())
    _times_summary(terminalreporter, exitstatus, config)


def _times_summary(terminalreporter, exitstatus, config):
    """With SKINSAFE_TEST_TIMES=FILE: the run's wall time, its outcome counts, the machine's busy and idle CPU seconds
    over the run (every process, not only the tests'), the 20 slowest tests (setup + call + teardown) and every test's
    [node id, wall s, CPU s, start s after the run's, worker] as JSON,
    the figures of docs/contributing.md (`SKINSAFE_TEST_TIMES=results/tests/times.json make test`)."""
    import json
    import os
    import time

    path = os.environ.get("SKINSAFE_TEST_TIMES")
    if not path or os.environ.get("PYTEST_XDIST_WORKER"):
        return
    per_test, counts, cpu, start = {}, {}, {}, {}
    for outcome, reports in terminalreporter.stats.items():
        for r in reports:
            if getattr(r, "when", None) in ("setup", "call", "teardown"):
                per_test[r.nodeid] = per_test.get(r.nodeid, 0.0) + r.duration
                if r.when == "teardown":
                    props = dict(r.user_properties)
                    cpu[r.nodeid] = props.get("cpu_s", 0.0)
                    start[r.nodeid] = (props.get("started"), props.get("worker"))
                if r.when == "call" or outcome == "skipped":
                    counts[outcome] = counts.get(outcome, 0) + 1
    slowest = sorted(per_test.items(), key=lambda kv: -kv[1])[:20]
    workers = getattr(config.option, "numprocesses", None) or 1
    busy, idle = _host_cpu_s()  # one reading of the machine's counters, for both figures
    from skinsafe.core.skin.files import atomic_write

    atomic_write(path, json.dumps({
        "date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count(), "workers": workers,
        "load_average": [round(x, 1) for x in os.getloadavg()], "exit_status": int(exitstatus),
        "wall_s": round(time.monotonic() - config._skinsafe_started, 1), "counts": counts,
        "cpu_s": round(sum(cpu.values()), 1),
        "host_busy_s": round(busy - config._skinsafe_host[0], 1), "host_idle_s": round(idle - config._skinsafe_host[1], 1),
        "rows": [{"test": k.split("::", 1)[1] if "::" in k else k, "file": k.split("::", 1)[0], "s": round(v, 1),
                  "cpu_s": round(cpu.get(k, 0.0), 1)} for k, v in slowest],
        "cpu_rows": [{"test": k.split("::", 1)[1] if "::" in k else k, "file": k.split("::", 1)[0],
                      "cpu_s": round(v, 1)} for k, v in sorted(cpu.items(), key=lambda kv: -kv[1])[:20]],
        "groups": _groups(per_test),
        "every_test": [[k, round(v, 2), round(cpu.get(k, 0.0), 2), *_started(start.get(k), config)]
                       for k, v in sorted(per_test.items())]}, indent=1))


def _groups(per_test: dict) -> dict:
    """xdist group -> the wall seconds of its tests (one worker runs a group's tests one after another)."""
    out = {}
    for k, v in per_test.items():
        if k.rfind("@") > k.rfind("]"):
            g = k.rsplit("@", 1)[1]
            out[g] = round(out.get(g, 0.0) + v, 1)
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def _started(at, config) -> list:
    """[seconds from the run's start, worker] of a test that reported when it started, else []."""
    if not at or at[0] is None:
        return []
    return [round(at[0] - config._skinsafe_started_epoch, 1), at[1]]
