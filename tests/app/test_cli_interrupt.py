"""Ctrl-C on any `skinsafe` command ends with exit 130 and one line, never a traceback: while the
command module imports (mujoco's C extension turns an interrupt into an ImportError there) and
while it runs."""
import signal
import subprocess
import sys
import time

import pytest


@pytest.mark.parametrize("delay", [0.2, 0.6, 1.2, 2.0])
def test_ctrl_c_exits_130_without_traceback(delay):
    proc = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.cli", "bench", "jacobians", "--sizes", ",".join(["16384"] * 60)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, (proc.returncode, err[-2000:])
    assert "Traceback" not in err
    assert err.strip().endswith("skinsafe: interrupted")
