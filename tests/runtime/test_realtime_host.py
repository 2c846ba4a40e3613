"""What `skinsafe run` refuses before it moves anything: the FR3 without real-time scheduling, and a link latency
above the free allowance, each unless a flag says so (exit 2, one line naming the flag)."""
import subprocess
import sys
from pathlib import Path

import pytest

SKINSAFE = str(Path(sys.executable).with_name("skinsafe"))


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([SKINSAFE, "run", *map(str, args)], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def skin(tmp_path_factory):
    path = tmp_path_factory.mktemp("rt") / "skin.json"
    subprocess.run([SKINSAFE, "sample", "--robot", "ur5", "--out", str(path)], check=True, capture_output=True)
    return path


@pytest.mark.parametrize("latency,allowed", [(0.2, False), (0.05, True), (0.2, True), (11.0, True)])
def test_link_latency_above_the_allowance_needs_its_flag(tmp_path, latency, allowed):
    # a map that is not there: the arguments are judged first, so the flag's verdict comes before the file's
    p = _run(tmp_path / "none.json", "--boards", "emulate", "--command", "hold", "--link-latency", latency,
             *(["--allow-link-latency"] if allowed else []))
    assert p.returncode == 2 and "Traceback" not in p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1
    if latency > 10:
        assert "--link-latency 11.0: give 0..10 s" in lines[0]
    elif not allowed:
        assert "--allow-link-latency" in lines[0]
    else:
        assert "none.json" in lines[0]  # past the latency check: the missing map is what stops it


def test_fr3_without_real_time_is_refused_before_connecting(skin):
    p = _run(skin, "--robot", "fr3", "--host", "127.0.0.1", "--boards", "/dev/ttyUSB9", "--command", "hold",
             "--realtime", "off")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    (line,) = p.stderr.strip().splitlines()
    assert "needs real-time scheduling (SCHED_FIFO)" in line and "--allow-non-realtime" in line
    assert "cannot connect" not in line  # refused before the driver tried the robot


def test_fr3_with_the_flag_goes_on_to_the_robot(skin):
    p = _run(skin, "--robot", "fr3", "--host", "127.0.0.1", "--boards", "/dev/ttyUSB9", "--command", "hold",
             "--realtime", "off", "--allow-non-realtime")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "WARNING: the FR3 without real-time scheduling" in p.stderr
    assert "needs real-time scheduling" not in p.stderr
    # no robot there, or (a franky-sim of another test listening) one whose joints are not the UR5 map's
    assert any(m in p.stderr for m in ("fr3: cannot connect to 127.0.0.1", "missing system part",
                                       "has no joint(s) fr3_joint1"))
