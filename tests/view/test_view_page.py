"""The live view in headless Chromium (Debian's `chromium`, driven by playwright; never a browser download):
`skinsafe run --view` with a scripted poke on a known taxel serves the page while the robot moves (the live
tick advances), and records the run; `skinsafe view` of that record: the timeline scrubs, "next contact"
jumps to the poke, the layer panel shows the retraction naming the taxel, and that taxel's pixels in a
screenshot turn hot (projected with the page's camera) where they were cold before the poke.
Boards at 10 Hz (silent after 200 ms) and the browser at nice 19: the shared machine stalls pseudo-terminals,
more so with a browser drawing WebGL in software (at normal priority a board was stopped as silent)."""
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.bench.browser import CHROMIUM_ARGS, chromium, niced
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.view_page import FOV, camera
from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.taxel_map import save

CHROMIUM = chromium()
W, H = 1200, 800
# the docs' picture of a poke: rewritten only when asked (SKINSAFE_PICTURES=1), else a test run leaves the tree clean
SCREENSHOT = Path(__file__).resolve().parents[2] / "results" / "view" / "view_poke.png"
POKE_S = 2.0  # robot seconds
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium: `apt-get install -y chromium` (.ci/run does)")


def project(p, eye, at, fov=FOV, w=W, h=H):
    """Pixel (x, y) of world point p for a pinhole camera at eye looking at `at`, z up (the page's camera)."""
    f = (at - eye) / np.linalg.norm(at - eye)
    s = np.cross(f, [0.0, 0.0, 1.0])
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    v = p - eye
    k = (h / 2) / (np.tan(fov / 2) * (v @ f))
    return w / 2 + k * (v @ s), h / 2 - k * (v @ u)


def hot_near(png: bytes, xy, r=14) -> int:
    """Pixels near xy that are hot on the page's scale (red to yellow)."""
    import io

    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    x, y = int(round(xy[0])), int(round(xy[1]))
    patch = a[max(0, y - r):y + r, max(0, x - r):x + r]
    return int(((patch[..., 0] > 190) & (patch[..., 2] < 120)).sum())


def cli(*args):
    return subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def url_of(proc) -> str:
    for line in proc.stdout:
        if line.startswith("skinsafe view:"):
            return line.rsplit(" at ", 1)[1].strip()
    raise AssertionError(f"the view did not start: {proc.stderr.read()[-2000:]}")


def live_t(page, timeout_s=60) -> float:
    """The robot time the live page shows (its status line `t = ... s`)."""
    text = page.get_by_text("t = ").first
    text.wait_for(timeout=timeout_s * 1000)
    return float(re.search(r"t = ([0-9.]+) s", text.inner_text()).group(1))


def settle(page, timeout_s=60):
    """Wait until the 3D canvas has drawn the skin (dark-blue taxels), not only the panel."""
    import io

    from PIL import Image

    for _ in range(int(timeout_s / 0.5)):
        a = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB")).astype(int)[:, :780]
        if ((a[..., 2] > 90) & (a[..., 0] < 70) & (a[..., 1] < 90)).sum() > 2000:
            return
        page.wait_for_timeout(500)
    raise AssertionError("the skin never appeared on the canvas")


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        # the browser at the lowest priority, as `run --view` starts its page process (nice 10): on this shared
        # 2-core machine software WebGL otherwise starves the emulated boards' pseudo-terminals (a board silent)
        b = p.chromium.launch(executable_path=niced(tmp_path_factory.mktemp("chromium"), CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


def live(browser, skin, taxel: int, record):
    """`skinsafe run --view --record` until Ctrl-C, the page's live tick advancing past the poke."""
    # runs until Ctrl-C: the live phase takes as long as this machine needs to draw the page, no longer
    run = cli("run", skin, "--boards", "emulate", "--command", "hold", "--rate", 10, "--tare-frames", 10,
              # held 0.5 s: the boards sample at 10 Hz on the host's clock, and a loaded host can run the sim's 0.13 s
              # of a default poke between two frames (seen once in `make test`: a record without a reading)
              "--contact", f"poke:at={POKE_S},taxel={taxel},hold=0.5", "--seconds", 120, "--record", record, "--view",
              "--view-port", 8391, "--view-stream", "127.0.0.1:0",  # (0: no page); taken: viser tries the next
              # the browser drawing 16k points in software WebGL can starve the boards' reader for seconds on
              # a 2-core machine (CI: 1.8 s once): this test is about the view; tests/runtime holds the watchdogs
              "--link-latency", 5, "--allow-link-latency")
    try:
        page = browser.new_page(viewport={"width": W, "height": H})
        for line in run.stderr:  # the page is served before the robot moves
            if "the view page at" in line:
                page.goto(line.rsplit(" at ", 1)[1].strip())
                break
        seen = [live_t(page)]
        while seen[-1] <= max(seen[0], POKE_S + 1.0):  # the live tick advances with the robot, past the poke
            assert run.poll() is None, run.stderr.read()[-2000:]
            page.wait_for_timeout(500)
            seen.append(live_t(page))
        assert seen == sorted(seen), seen
        run.send_signal(signal.SIGINT)
        out, err = run.communicate(timeout=60)
    except Exception as e:
        run.send_signal(signal.SIGINT)  # the run ends its page process (SIGKILL would leave it behind)
        raise AssertionError(f"the live phase failed ({e}); the run said: {run.communicate(timeout=60)[1][-2000:]}") from e
    assert run.returncode == 130 and "STOPPED by the operator" in err, err[-2000:]
    page.close()


def test_run_view_live_then_the_record_scrubs_to_the_poke_and_the_taxel_turns_hot(tmp_path, browser, realtime_turn):
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    skin = save(design, tmp_path / "skin.json")
    kin = TaxelKinematics(robot.model, design)
    pos, frames = kin.poses(robot.home)
    eye, at = camera(pos)
    # the taxel to poke: facing the camera, among the most visible (its normal toward the eye), on the forearm side
    facing = np.einsum("ki,ki->k", frames[:, :, 2], (eye - pos) / np.linalg.norm(eye - pos, axis=1, keepdims=True))
    taxel = int(np.argmax(facing))
    record = tmp_path / "poke.mcap"
    # `run` pins its loop to the first core at SCHED_FIFO: never beside another real-time run (the slot held for the
    # live phase only; the record's replay after it runs beside the real-time tests)
    with realtime_turn():
        live(browser, skin, taxel, record)

    view = cli("view", record, "--port", 0, "--seconds", 120)  # any free port: `url_of` reads it back
    try:
        page = browser.new_page(viewport={"width": W, "height": H})
        page.goto(url_of(view))
        page.get_by_text("retraction:").wait_for(timeout=60000)
        settle(page)
        xy = project(pos[taxel], eye, at)
        assert 0 < xy[0] < 780 and 0 < xy[1] < H, xy  # in the canvas, left of the panel
        cold = page.screenshot()
        assert page.get_by_text("retraction: ACTIVE").count() == 0
        page.get_by_role("button", name="next contact").click(timeout=90000)
        page.get_by_text("retraction: ACTIVE").wait_for(timeout=60000)
        body = page.inner_text("body")
        assert f"first {taxel})" in body or f"on taxel {taxel}" in body, body[:600]
        assert hot_near(cold, xy) == 0
        for _ in range(60):  # the colours follow the panel
            hot = page.screenshot()
            if hot_near(hot, xy) >= 4:
                break
            page.wait_for_timeout(500)
        assert hot_near(hot, xy) >= 4, f"taxel {taxel} at pixel {xy} is not hot"
        # never half a PNG to a reader (the docs' clone copying results/)
        atomic_write(SCREENSHOT if os.environ.get("SKINSAFE_PICTURES") else tmp_path / SCREENSHOT.name, hot)
        # scrub back to the start: the retraction and the heat are gone again
        page.get_by_role("slider").first.focus()
        page.keyboard.press("Home")
        page.get_by_text("retraction: idle").wait_for(timeout=60000)
        assert "t = 0.000 s" in page.inner_text("body")
    finally:
        view.terminate()
        view.wait(10)
