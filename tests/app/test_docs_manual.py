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
                      r"\b(?:Python|Blender|bpy|PyTorch|MuJoCo|KiCad|franky-sim|numpy|libfranka|Chromium|ROS)(?: version)?)"
                      r"\s*[A-Z]?\d[\d.]*[a-z]?(?:\s*(?:,|-|–|and|or|to|/)\s*[A-Z]?\d[\d.]*[a-z]?)*|\(N(?:, \d+)+\)|"
                      r"\b[A-Z][a-z]+(?: et al\.)? (?:19|20)\d\d\b|\b\d-?D\b")
NUMBER = re.compile(r"(?<![\w.])(?<![A-Za-z]-)\d[\d,]*(?:\.\d+)?")

# Pages that still hold numbers written by hand (measurements pasted from a run, settings restated in words): the
# most each may hold. Fill them with fig:value / fig:table (core/app/readme.py) or a composite figure the build
# computes, and lower the count; a page not listed holds none.
HAND_WRITTEN = {
    "README.md": 5, "docs/benchmarks.md": 444, "docs/contributing.md": 9, "docs/deploy/index.md": 18,
    "docs/design/addon.md": 10, "docs/design/blender.md": 29, "docs/design/buildable.md": 29,
    "docs/design/cli.md": 27, "docs/design/fabrication.md": 31, "docs/design/jacobians.md": 2,
    "docs/design/robots.md": 51, "docs/reference/formats.md": 2, "docs/run/fr3.md": 65, "docs/run/index.md": 111,
    "docs/run/live.md": 42, "docs/run/ros2.md": 18, "docs/run/safety.md": 137, "docs/simulate/defensiveness.md": 97,
    "docs/simulate/index.md": 4, "docs/simulate/pfl.md": 225, "docs/simulate/trade.md": 18,
}
# owned by #51 (learning numbers filled from results there)
LEARNING_PAGES = {"docs/simulate/strategy.md", "docs/simulate/modulation.md", "docs/paper/learning.md"}


def hand_written(text: str) -> list[str]:
    """Each number in `text`'s prose and tables that no figure marker fills and that is no constant, with context."""
    t = CONSTANT.sub(" ", prose(text))
    return [f"{m.group()}: ...{' '.join(t[max(0, m.start() - 40):m.end() + 20].split())}..." for m in NUMBER.finditer(t)]


def test_numbers_from_results_and_constants_pass_and_hand_written_ones_are_found():
    text = ("Took <!-- fig:value results/r.json wall_s:mins -->3 min 39 s<!-- /fig --> (Fig. 7, 8 and 12; eq. 10-13; "
            "ISO/TS 15066; exit 1; Python 3.11; `--period 0.002`; (N, 3) array; Flacco et al. 2012; the 3-D form; a 3D panel)."
            "\n\n1. a step\n\n"
            "```bash\nskinsafe run --seconds 3\n```\n")
    assert hand_written(text) == []
    found = hand_written("The sensing kernel costs 0.253 of the step, 189x faster, on 2,149 taxels.")
    assert [f.split(":")[0] for f in found] == ["0.253", "189", "2,149"]


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


@pytest.mark.parametrize("page", sorted(set(PAGES) - LEARNING_PAGES - {"docs/changelog.md"}))
def test_a_page_writes_no_number_by_hand(page):
    found = hand_written(PAGES[page])
    allowed = HAND_WRITTEN.get(page, 0)
    assert len(found) <= allowed, (
        f"{page}: {len(found)} numbers written by hand (at most {allowed}); fill them from a results file "
        f"(<!-- fig:value FILE PATH -->, core/app/readme.py) or name the constant in CONSTANT:\n" + "\n".join(found))


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
