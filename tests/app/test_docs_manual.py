"""The docs read as a manual: the present tense (history lives in CHANGELOG.md), numbers that come from results files
or the build, tables a reader can take in, every results picture shown where its topic is, and an API reference
that covers what the pages' examples import. Text checks only: no build, no results re-made."""
import re
from pathlib import Path

import pytest

from skinsafe.core.app.readme import FENCE, MARKER, FigureError, fill, pages

ROOT = Path(__file__).resolve().parents[2]
PAGES = {p.relative_to(ROOT).as_posix(): p.read_text() for p in pages(ROOT)}
HISTORY_EXEMPT = {"docs/changelog.md"}  # includes CHANGELOG.md: the history is its subject


def prose(text: str) -> str:
    """What a page says in words: without code (blocks and spans), figures filled from results (their markers and
    text), comments, link targets, HTML tags, URLs, snippet includes, list and step numerals."""
    text = re.sub(r"^--8<--.*$", " ", text, flags=re.M)
    text = FENCE.sub(" ", text)
    text = MARKER.sub(" ", text)
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    text = re.sub(r"`[^`]*`", " ", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    text = re.sub(r"</?[A-Za-z][^>]*>", " ", text)
    text = re.sub(r"https?://\S+", " ", text)
    text = re.sub(r"^(\s*)\d+\.\s", r"\1", text, flags=re.M)  # an ordered list's numerals
    return re.sub(r"^(#+\s*|\*\*)\d+\.\s", r"\1", text, flags=re.M)  # "## 1. Design", "**1. Design.**"


# --- (a) the present tense ------------------------------------------------------------------------------------------

HISTORY = re.compile(r"\bissues?\s+#?\d+|(?<![\w&/])#\d+\b|\bearlier\b|\bpredates?\b|"
                     r"(?<!\bis )(?<!\bare )(?<!\bbe )(?<!\bwas )(?<!\bwere )(?<!\bbeen )\bused to\b", re.I)


def history(text: str) -> list[str]:
    """Each place `text` names an issue or speaks of the past ("earlier", "predates", "used to"), with its context."""
    t = prose(text)
    return [" ".join(t[max(0, m.start() - 50):m.end() + 30].split()) for m in HISTORY.finditer(t)]


def test_history_words_are_found_and_present_tense_is_not():
    assert len(history("Fixed in issue 41; see #50. The grid predates the tuner. It used to be slow; earlier runs "
                       "stalled.")) == 5
    assert history("It is used to compute the stop. `issue 41` in code, [a link](https://x.org/issues/8189), "
                   "an anchor [here](#who-can-drive).") == []


@pytest.mark.parametrize("page", sorted(set(PAGES) - HISTORY_EXEMPT))
def test_a_page_describes_the_current_state(page):
    found = history(PAGES[page])
    assert not found, f"{page}: history belongs in CHANGELOG.md (the docs describe the current state): {found}"


# --- (b) numbers come from results files or the build -------------------------------------------------------------

# Numbers that are names or constants, never results: a reference into the paper or a standard (Fig. 12, eq. 10-13,
# Table A.3, section III-C, ISO 10218, ISO/TS 15066, IEC 60204-1), a protocol version (hardware/PROTOCOL.md), an
# exit code (`skinsafe run`'s, core/app/run.py), a software version (pinned in pyproject.toml and the Makefile), an
# array's shape ((N, 3)), a cited paper's year (Flacco et al. 2012), a dimension (3-D, 6-D, 3D).
CONSTANT = re.compile(r"(?:\bFigs?\.|\bFigures?|\b[Ee]qs?\.|\bequations?|\bTables?|\b[Ss]ections?|\bISO(?:/TS)?|\bIEC|"
                      r"\bprotocol version|\bexits?(?: codes?)?|"
                      r"\b(?:Python|Blender|bpy|PyTorch|MuJoCo|KiCad|franky-sim|numpy|libfranka|Chromium|ROS|glibc|"
                      r"rerun-sdk|pyarrow|wgpu|Apache|firmware|versions?)(?: version)?)"
                      r"\s*[A-Z]?\d[\d.]*[a-z]?(?:\s*(?:,|-|–|and|or|to|/)\s*[A-Z]?\d[\d.]*[a-z]?)*|\(N(?:, \d+)+\)|"
                      r"\b[A-Z][a-z]+(?: et al\.)?\s+(?:19|20)\d\d\b|\b\d-?D\b")
NUMBER = re.compile(r"(?<![\w.])(?<![A-Za-z]-)\d+(?:,\d{3})*(?:\.\d+)?")
# Numbers that name something rather than report it: a grid or an array's size (8x8 modules, 16 × 16, 6 × nv), a
# compound adjective (a 2-core machine, a 256-taxel module, a 32-bit field), an ordinal (the 99th percentile), a
# release (bpy 4.5.15, firmware 2.0.0), a stated bound (a target, limit or tolerance: ≤ 0.5 ms, within 1 mm, more than 2 mm, ±5%), a
# confidence level (95% interval), a process's niceness (nice 19), an exponent (K L^2), a tolerance in scientific notation (to 1e-6).
NAME = re.compile(r"(?<![\d,.])\d+\s*[x×]\s*(?:\d+|N|nv)\b(?![,.]\d)|\b\d[\d.]*-(?=[A-Za-z])|\b\d+(?:st|nd|rd|th)\b|"
                  r"\b\d+\.\d+\.\d+\+?|(?:≤|≥|<=|>=|<|>|±|\bat most|\bat least|\bwithin|\b(?:more|less|fewer) than)\s*[-+−]?\d[\d,.]*|"
                  r"\b\d+%\s+(?:confidence\s+|Student-t\s+)?(?:intervals?|CI)\b|\bnice -?\d+|\^-?\d+|\bx86-64\b|\b\d+\.\d+ LTS\b|\b\d(?:\.\d+)?e[-+−]?\d+\b")

# Constants a page states that no code holds, one (number, source) pair each: a datasheet, a standard, a cited
# paper, an example's argument. A number listed here passes on its page only.
CONSTANTS: dict[str, dict[str, str]] = {
    "README.md": {"3.13": "Blender 5.3's Python (the Makefile's bpy-only environments)",
                  "1": "the tour's command below (poke:at=1.0)"},
    "docs/contributing.md": {"0": "core 0 and port 0: the loop's pinned core (core/realtime.py), the kernel's free port",
                             "6": "the suite's time target (make test)", "9": "a fresh clone's time target (.ci/run)"},
    "docs/design/addon.md": {"4": "the camera's margin (addon/headless.py: 1.08 of the extent)",
                             "1.5": "the dots' lift off the link (addon/headless.py: lift=0.0015)"},
    "docs/deploy/index.md": {**{c: "an exit code of deploy and stream (hardware/cli_deploy.py EXIT_CODES)"
                                for c in ("0", "2", "130", "143")},
                             "1": "an exit code (hardware/cli_deploy.py EXIT_CODES) and the link's default 1 Mbaud "
                                  "(hardware/client.py baud)",
                             "24": "a config's header bytes (hardware/PROTOCOL.md)",
                             "12": "a config entry's bytes (hardware/PROTOCOL.md)",
                             "22": "a frame's header bytes (hardware/PROTOCOL.md)",
                             "16": "a frame's fixed payload fields (hardware/PROTOCOL.md)"},
    "docs/design/buildable.md": {"3": "polyimide's yield strain (DuPont Kapton HN datasheet)",
                                 "4,000": "the exposed surface's samples (core/design/cover.py, exposed(n=4000))",
                                 "60": "bench fab's coverage threshold (core/app/bench_fab.py: covered < 0.6)",
                                 "90": "a flange's right-angle rim (the descriptions' geometry)",
                                 "65,536": "the taxel-id rule (core/skin/ids.py: SHIFT = 16)",
                                 "0": "the first id of the other rule (0..N-1)"},
    "docs/design/blender.md": {"0.01": "the field's unit, a fraction (0.01 = 1%)", "1": "the field's unit (0.01 = 1%)",
                               "15": "the wheel's step (addon/place_tool.py: STEP = radians(15))",
                               "65,536": "the taxel-id rule (core/skin/ids.py: SHIFT = 16)",
                               "0": "the first id of the older rule (0..N-1)",
                               "2": "the table's test move (tests/addon/test_addon_object_menu.py)",
                               "40": "the UR5 forearm capsule's radius (addon/headless.py: 0.04 m)"},
    "docs/design/cli.md": {"1": "the enclosure test's ray start (core/design/audit.py enclosed: 1 mm above)",
                           "45": "the enclosure test's ray tilt (core/design/audit.py: radians([45, 80]))",
                           "80": "the enclosure test's ray tilt (core/design/audit.py: radians([45, 80]))",
                           "4": "the cover's spacing (core/design/cover.py: 0.75 pitch)",
                           "7": "the Franka's link names (panda_link3 to panda_link7)"},
    "docs/design/fabrication.md": {"10": "the sheet's scale bar (exporters/fab.py: 10 mm)",
                                   "1": "the sheet's scale (1 unit = 1 mm, 1:1) and a pin's number (pin k + 1)",
                                   "0": "the module centre's coordinate (exporters/fab.py)",
                                   "2": "half a pitch in the pad formula (exporters/fab.py)",
                                   "100": "the KiCad page's module origin (exporters/fab.py KICAD_ORIGIN_MM)",
                                   "1000": "metres to millimetres",
                                   "65,536": "the taxel-id rule (core/skin/ids.py: SHIFT = 16)"},
    "docs/design/robots.md": {"7": "the arms' degrees of freedom (their descriptions)",
                              "4": "the Panda's joint 4 (core/robot/models.py PANDA_RANGE) and poke --map's least "
                                   "taxels (core/experiments/poke.py: c >= 4)",
                              "0": "the zero pose the Panda's joint 4 excludes (core/robot/models.py PANDA_RANGE)",
                              "45": "the normals' crease angle (core/design/surface.py: crease_deg=45.0)"},
    "docs/simulate/strategy.md": {"0": "trial 0, the published defaults (core/experiments/maze.py DEFAULTS_SOURCE)",
                                  "1": "the shrinkage formula's 1 - w (core/learn/agents.py VisitCounts)",
                                  "0.15": "recovery-rl's maze eps_risk (scripts/maze.sh)",
                                  "0.5": "recovery-rl's maze gamma_safe (scripts/maze.sh)",
                                  "100": "recovery-rl's SQRL nu (arg_utils.py)"},
    "docs/paper/learning.md": {"1": "one thread per task (core/experiments/runner.py), a cosine's end, T = 1 and "
                                    "replicate 1's name",
                               "0": "trial 0, the published defaults (core/experiments/maze.py), augment 0 "
                                    "(core/experiments/tracking_runs.py) and a cosine's zero",
                               "2": "replicate 2's name"},
    "docs/simulate/modulation.md": {"0": "the potential's range [0, 1] and tangent_gain's off (core/safety/modulation.py)"
                                         " and augment 0 (core/experiments/tracking_runs.py)",
                                    "1": "the potential's range [0, 1] and the paper's eigenvalue 1 (eq. 14)",
                                    "2": "an example's control period (2 ms)",
                                    "10": "an example's control period (10 ms)",
                                    "6": "the claim's episodes 6-10 (core/experiments/tracking.py)",
                                    "3,000": "the desk's --samples default (core/experiments/scenes.py)",
                                    "8": "the distance labels' ramp (core/experiments/tracking_runs.py: ramp 0.08 m)"},
    "docs/run/live.md": {"20": "--fps's default (core/app/view.py)",
                         "30": "the tap's rate (core/runtime/view_share.py: rate_hz=30.0)",
                         "2": "the silence watchdog's frame periods (core/runtime/monitor.py silence_s)",
                         "10": "the live plot's window (core/runtime/view_page.py HISTORY_S)",
                         "0": "the record's start (t = 0)"},
    "docs/run/fr3.md": {"2": "the hand's period (core/sim/franky_world.py Hand.period: 2 s) and the machine's cores",
                        "1": "the robot's 1 kHz clock (hardware/franka.py PERIOD_S)",
                        "5": "the frame -> command latency bound (issue #50's worst tick, docs/run/index.md)"},
    "docs/simulate/defensiveness.md": {"0": "the formulas' s = 0 and epsilon's range [0, 1] (core/safety/retraction.py)",
                                       "1": "the formulas' N + 1 and epsilon's range [0, 1]",
                                       "2": "the brake's distance formula dt (N + 1) / 2 (core/safety/viability.py)"
                                            " and Fig. 7's contact counts (core/experiments/poke.py)",
                                       "3": "Fig. 7's contact counts (core/experiments/poke.py)",
                                       "8": "the bench's contacts (core/bench/modulation.py)",
                                       "128": "the bench's hidden units (core/bench/modulation.py)",
                                       "10": "T's least control periods (core/safety/defensiveness.py: 10 * dt)",
                                       "0.5": "the figure's merge epsilons (core/experiments/poke.py)",
                                       "12": "eq. 10's alpha / 12 (the paper)"},
    "docs/run/index.md": {"1": "the first command's poke:at=1.0 and the CRC storm's window (core/runtime/monitor.py)",
                          "100": "--rate's default (core/runtime/run_config.py) and the teleop sender's "
                                 "(core/app/teleop_send.py)",
                          "0.5": "this page's commands' --link-latency 0.5",
                          "2": "the silence bound's frame periods (core/runtime/monitor.py silence_s), the robot "
                               "state's periods (core/runtime/loop.py state_periods=2) and the hijack test's 2^30",
                          "0": "the zero force of an excluded taxel, a clip at zero, a first time 0 and an age 0",
                          "5": "the CRC storm's corrupt frames (core/runtime/monitor.py)",
                          "143": "SIGTERM's exit code (core/app/run.py EXIT_CODES)",
                          "3": "the trajectory's gain (core/safety/stack.py TrajectorySource)",
                          "0.15": "the trajectory's error clip (core/safety/stack.py TrajectorySource)",
                          "0600": "the key file's mode (core/runtime/teleop.py)",
                          "0.1": "the hijack test's window (tests/runtime/test_teleop.py)",
                          "0.8": "the hijack test's window (tests/runtime/test_teleop.py)",
                          "0.4": "the hijack test's target (tests/runtime/test_teleop.py)",
                          "10": "the diagnostics' rate (core/runtime/recording.py)"},
    "docs/run/ros2.md": {"2": "record version 2 (core/runtime/record_read.py)"},
    "docs/run/safety.md": {"2": "the zero's response periods and the robot state's periods (core/runtime/monitor.py, "
                                "core/runtime/loop.py state_periods=2), the jerk term's factor, IEC 60204-1's stop "
                                "category 2, the sim's default period (core/runtime/run_config.py) and the cores",
                           "0": "IEC 60204-1's stop category 0, --overruns 0 (off) and the picture's scale's start",
                           "1": "IEC 60204-1's stop category 1, the FR3's 1 ms period (hardware/franka.py), a "
                                "poke at 1 s (the storm's) and named_as_injected's whole",
                           "3": "--overruns' default (core/runtime/monitor.py OVERRUNS) and the overrun tests' "
                                "3 periods (tests/runtime/test_runtime_safety.py)",
                           "50": "the storm's --rate default (core/app/runtime_faults.py)",
                           "10": "ctrl-c-twice's gap (core/app/runtime_faults.py SIGNALS) and the FR3's ramp "
                                 "(hardware/franka.py QDD_MAX)",
                           "5": "the FR3 skin's links 5 and 6, the detection bound's 5 ms (core/runtime/monitor.py "
                                "HANDOFF_S) and the latency target (docs/run/index.md)",
                           "6": "the FR3 skin's links 5 and 6 (core/app/runtime_faults.py: design --bodies fr3_link5,fr3_link6)",
                           "32": "the taxels of the FR3 skin's design (core/app/runtime_faults.py: design --bodies fr3_link5,fr3_link6)",
                           "0600": "the key file's mode (core/runtime/teleop.py)"},
    "docs/simulate/pfl.md": {**{n: "ISO/TS 15066 Annex A (core/sim/body_regions.py REGIONS), its Tables A.2 and A.3"
                                for n in ("2", "4.4", "420", "280", "220", "360", "300", "320", "150", "10", "0.6",
                                          "75", "40")},
                             "8.8": "the head's mass in pre-ISO/TS 15066 tables (ISO/TS 15066 Table A.3 gives 4.4)",
                             "2025": "ISO 10218-2:2025's year",
                             "6": "a body Jacobian's rows (core/safety/pfl.py)",
                             **{n: "core/experiments/collaboration.py's defaults (its --help) and the scenario's "
                                   "sweep (core/experiments/collaboration_scenario.py)"
                                for n in ("1.6", "1", "1.5", "50", "5.5", "0.5", "0.3", "0.8", "0", "0.25",
                                          "1,500", "3,000")}},
    "docs/benchmarks.md": {**{n: "the benches' sizes and targets (the Targets table above; core/bench/*.py --taxels)"
                              for n in ("4,096", "16,384", "10,000", "8", "128", "10")},
                           "1": "the link's 1 Mbaud (hardware/client.py baud) and the stream's 1 kHz (bench serial)",
                           "5": "the probes' depth (core/sim/probes.py DEPTH) and the view's ±5% target",
                           "20": "the benches' blocks of 20 ticks (core/bench/retraction.py) and the storm's duplicate-uid rounds",
                           "6": "an arm's joints (a 6- or 7-joint arm)",
                           "0": "zero hidden units and the CPU latency request's 0 (/dev/cpu_dma_latency)",
                           "7": "the tactile points per taxel (core/sim/scene.py TACTILE_POINTS)",
                           "19": "the tactile points per taxel (core/sim/scene.py TACTILE_POINTS)",
                           "99": "the 99.9th percentile's name",
                           **{n: "the fault storm's defaults (core/bench/serial_faults.py FAULTS and --help, "
                                 "core/bench/stream_faults.py STREAM_FAULTS, SURE, HANG_S)"
                              for n in ("100", "25", "4", "40", "200", "0.2", "0.3", "4,294,967,295", "70", "11",
                                        "60", "0.4", "13", "2", "130")}},
}


def hand_written(text: str, allowed: dict[str, str] | None = None) -> list[str]:
    """Each number in `text`'s prose and tables that no figure marker fills, that is no constant or name, and that
    `allowed` (the page's CONSTANTS) does not list, with its context."""
    t = NAME.sub(" ", CONSTANT.sub(" ", prose(text)))
    return [f"{m.group()}: ...{' '.join(t[max(0, m.start() - 40):m.end() + 20].split())}..." for m in NUMBER.finditer(t)
            if m.group() not in (allowed or {})]


def test_numbers_from_results_and_constants_pass_and_hand_written_ones_are_found():
    text = ("Took <!-- fig:value results/r.json wall_s:mins -->3 min 39 s<!-- /fig --> (Fig. 7, 8 and 12; eq. 10-13; "
            "ISO/TS 15066; exit 1; Python 3.11; `--period 0.002`; (N, 3) array; Flacco et al. 2012; the 3-D form; a 3D panel; "
            "8x8 and 16 × 16 modules on a 2-core machine, the 99th percentile, bpy 4.5.15, ≤ 0.5 ms, within 1 mm, "
            "the 95% interval, nice 19, to 1e-6, more than 2 mm, K L^2, x86-64, the 4.5 LTS)."
            "\n\n1. a step\n\n"
            "```bash\nskinsafe run --seconds 3\n```\n")
    assert hand_written(text) == []
    found = hand_written("The sensing kernel costs 0.253 of the step, 189x faster, on 2,149 taxels.")
    assert [f.split(":")[0] for f in found] == ["0.253", "189", "2,149"]
    assert [f.split(":")[0] for f in hand_written("At 280 N and 0.253.", {"280": "ISO/TS 15066"})] == ["0.253"]


def test_every_listed_constant_names_its_source_and_is_on_its_page():
    for page, pairs in CONSTANTS.items():
        assert page in PAGES, f"CONSTANTS lists {page}, which is no page"
        stated = set(NUMBER.findall(prose(PAGES[page])))
        for number, source in pairs.items():
            assert NUMBER.fullmatch(number) and len(source.split()) >= 2, f"{page}: {number!r} needs a source named"
            assert number in stated, f"{page}: CONSTANTS lists {number}, which the page no longer states: drop it"


def test_a_setting_is_quoted_from_the_code_itself():
    from skinsafe.core.runtime.run_config import LINK_LATENCY_FREE, RunConfig

    text = ("<!-- fig:const skinsafe.core.runtime.run_config RunConfig.max_excluded:.0% -->x<!-- /fig --> "
            "<!-- fig:const skinsafe.core.runtime.run_config LINK_LATENCY_FREE*1000:g -->x<!-- /fig -->")
    new, changed = fill(text)
    assert len(changed) == 2 and f"-->{RunConfig.max_excluded:.0%}<!--" in new and \
        f"-->{LINK_LATENCY_FREE * 1000:g}<!--" in new and hand_written(new) == []
    from skinsafe.hardware.franka import QD_MAX

    new, _ = fill("<!-- fig:const skinsafe.hardware.franka QD_MAX.max -->x<!-- /fig -->")  # a numpy array, reduced
    assert f"-->{QD_MAX.max():g}<!--" in new
    with pytest.raises(FigureError, match="no 'nope' in 'skinsafe.core.runtime.run_config.RunConfig.nope'"):
        fill("<!-- fig:const skinsafe.core.runtime.run_config RunConfig.nope -->1<!-- /fig -->")
    with pytest.raises(FigureError, match="no module 'skinsafe.nowhere'"):
        fill("<!-- fig:const skinsafe.nowhere X -->1<!-- /fig -->")


@pytest.mark.parametrize("page", sorted(set(PAGES) - {"docs/changelog.md"}))
def test_a_page_writes_no_number_by_hand(page):
    found = hand_written(PAGES[page], CONSTANTS.get(page))
    assert not found, (
        f"{page}: {len(found)} numbers written by hand; fill each from a results file (<!-- fig:value FILE PATH -->, "
        f"core/app/readme.py), quote the code (<!-- fig:const MODULE NAME -->), list a constant with its source in "
        f"CONSTANTS, or write the sentence without it:\n" + "\n".join(found))


# --- (c) tables a reader can take in --------------------------------------------------------------------------------

MAX_COLUMNS = 8


def wide_tables(text: str) -> list[str]:
    """The header of each Markdown table in `text` (figures filled) with more than MAX_COLUMNS columns."""
    lines, wide = FENCE.sub("", text).splitlines(), []
    for head, rule in zip(lines, lines[1:]):
        if "|" in head and re.fullmatch(r"\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*", rule):
            cells = re.sub(r"`[^`]*`", "x", head.replace("\\|", "x")).strip().strip("|").split("|")
            if len(cells) > MAX_COLUMNS:
                wide.append(f"{len(cells)} columns: {head[:100]}")
    return wide


def test_a_wide_table_is_found():
    narrow = "| a | `b | c` | d |\n| --- | --- | ---: |\n| 1 | 2 | 3 |\n"
    assert wide_tables(narrow) == []
    assert wide_tables("| " + " | ".join("abcdefghi") + " |\n|" + "---|" * 9 + "\n") == ["9 columns: | a | b | c | d | "
                                                                                        "e | f | g | h | i |"]


@pytest.mark.parametrize("page", sorted(set(PAGES) - {"docs/changelog.md"}))
def test_no_table_is_wider_than_a_reader_takes_in(page):
    assert not wide_tables(PAGES[page]), f"{page}: tables over {MAX_COLUMNS} columns (show the key columns and link " \
                                         f"the results file for every column): {wide_tables(PAGES[page])}"


# --- (d) every results picture on its topic's pages -----------------------------------------------------------------

# results/<area>/ -> the docs folder whose pages own that area's pictures
TOPIC = {"design": "docs/design", "poke": "docs/simulate", "desk": "docs/simulate", "collaboration": "docs/simulate",
         "maze": "docs/simulate", "tracking": "docs/simulate", "runtime": "docs/run", "view": "docs/run", "run": "docs/run",
         "trade": "docs/simulate"}


def test_every_results_picture_is_shown_on_its_topics_pages():
    """An area's own pictures (results/<area>/*.png; its subfolders hold reduced runs and sweeps) are each shown as
    an image on a page of the area's docs folder."""
    areas = {p.parent.name for p in (ROOT / "results").glob("*/*.png")}
    assert areas - set(TOPIC) == set(), f"results areas with pictures and no docs folder in TOPIC: {areas - set(TOPIC)}"
    missing = []
    for png in sorted((ROOT / "results").glob("*/*.png")):
        rel, folder = png.relative_to(ROOT).as_posix(), TOPIC[png.parent.name]
        shown = [p for p, text in PAGES.items() if p.startswith(folder + "/")
                 and re.search(r"(!\[[^\]]*\]\(|<img [^>]*src=\")" + re.escape(rel), text)]
        if not shown:
            missing.append(f"{rel} (on a page of {folder}/)")
    assert not missing, f"pictures the results hold that no page of their topic shows: {missing}"


# --- the API reference covers what the examples import ---------------------------------------------------------------

def test_the_api_reference_documents_every_module_the_examples_import():
    api = PAGES["docs/reference/api.md"]
    documented = set(re.findall(r"^::: (\S+)", api, re.M))
    code = "\n".join(m.group(0) for text in PAGES.values() for m in re.finditer(r"^```python\n.*?^```", text, re.S | re.M))
    imported = set(re.findall(r"^\s*from (skinsafe\.\S+) import", code, re.M))
    assert imported, "no Python example imports skinsafe: the check would hold for nothing"
    assert imported <= documented, f"docs/reference/api.md lacks modules the examples import: {imported - documented}"


# --- what a safety tool must say ---------------------------------------------------------------------------------------

def test_the_index_the_run_pages_and_the_readme_say_what_skinsafe_is_not():
    statement = (ROOT / "docs" / "snippets" / "safety.txt").read_text()
    assert "does not replace the robot's own safety functions" in statement and "ISO 10218" in statement
    pages_ = ["docs/index.md"] + [p for p in PAGES if p.startswith("docs/run/")]
    lacking = [p for p in pages_ if '--8<-- "docs/snippets/safety.txt"' not in PAGES[p]]
    assert len(pages_) > 2 and not lacking, f"pages without the safety statement (include docs/snippets/safety.txt): {lacking}"
    readme = " ".join(PAGES["README.md"].split())
    assert "does not replace the robot's own safety functions" in readme and "ISO 10218" in readme
