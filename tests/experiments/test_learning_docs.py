"""The learning pages quote no result by hand: every number in their results prose is filled from a results
file (a `fig:` marker, `core/app/readme.py`) or is a constant of the protocol, named below with the code
it comes from (checked against that code, so a changed constant fails here until the page follows)."""
import re

import pytest

from skinsafe.core.app.readme import FENCE, MARKER, REPO
from skinsafe.core.experiments import maze, maze_claims, tracking, verdicts

# page -> the sections checked: (first heading, the heading that ends it; None: the page's end)
PAGES = {
    "docs/paper/index.md": [("# Reproduce the paper", None)],
    "docs/paper/learning.md": [("# Learning results", "### The n-step grid"), ("## Verdicts", None)],
    "docs/simulate/strategy.md": [("## Run the maze experiment", "## Cost: where a run's time goes"), ("### The budget", None)],
    "docs/simulate/modulation.md": [("## Learning the modulation (Fig. 11)", "## Fig. 14: the desk")],
}
FULL = maze.MazeConfig()
RUNS = tracking.TrackingConfig().run
# a number the pages may state, and the code it comes from
CONSTANTS = {
    "0.8": maze_claims.LEARNED_AT, "20": maze_claims.LAST, "10": maze_claims.WINDOW, "60": FULL.episodes,
    "4": FULL.trials, "2": FULL.replicates, "200": FULL.max_steps, "9": len(maze.METHODS), "72": 9 * FULL.trials * FULL.replicates,
    "144": 9 * len(FULL.eval_seeds) * FULL.replicates, "8": len(FULL.eval_seeds), "10-17": f"{FULL.eval_seeds[0]}-{FULL.eval_seeds[-1]}",
    "30": FULL.ablation_episodes, "68": round(maze.cpo_budget(1)), "4,000": f"{maze.SPACES['RRL']['offline_transitions'][0]:,}",
    "0.05": verdicts.ALPHA, "95%": "95%", "10%": tracking.SHARE * 100, "0.1": tracking.SHARE, "3": RUNS.n_balls,
    "0": RUNS.augment, "300": RUNS.duration / RUNS.control_dt, "10-19": "10-19", "20-29": "20-29", "0-2": "0-2", "1": 1,
    "8 cm": f"{RUNS.ramp * 100:.0f} cm", "0.05 rad": f"{RUNS.state_noise} rad", "5": 5, "0.1 s": "0.1 s",
    "8,000": 8000, "80%": maze_claims.LEARNED_AT * 100, "0.15 s": f"{RUNS.rollout_dt} s", "6-10": "6-10",
}
SOURCES = {  # where the constants that are not read from code above come from
    "10-19": "tracking.HELD_OUT", "20-29": "tracking.REPLICATE", "0-2": "the seeds the tracking scene was developed on",
    "1": "one (a count)", "5": "tracking_runs.PROBE (5 ticks)", "0.1 s": "tracking_runs.PROBE x control_dt", "95%": "the intervals' level",
    "8,000": "the budget the full grids are sized to", "6-10": "tracking._late: episodes 6-10",
}
REFERENCE = re.compile(r"\b(?:Figs?\.|eq\.|issues?|III-[A-C]|#)\s*\d+[a-z]?(?:/\d+[a-z]?|,\s*\d+[a-z]?|-\d+[a-z]?|-[a-z]\b)*"
                       r"|\btdm\d@[\d.]+s|\bT = \d|\bUR5e?\b|\bFR3\b|^\s*\d+\.\s", re.M)
NUMBER = re.compile(r"(?<![\w.\-])(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:-\d+)?(?: ?(?:%|cm|rad|s)\b|%)?")


def prose(page: str) -> str:
    text = (REPO / page).read_text()
    parts = []
    for first, end in PAGES[page]:
        a = text.index(first)
        parts.append(text[a:text.index(end, a) if end else len(text)])
    out = "\n".join(parts)
    for pattern in (MARKER, FENCE, re.compile(r"<!--.*?-->", re.S), re.compile(r"</?[A-Za-z][^>]*>"), re.compile(r"`[^`]*`"),
                    re.compile(r"\]\([^)]*\)"), REFERENCE):
        out = pattern.sub(" ", out)
    return out


def test_constants_match_the_code():
    for text, value in CONSTANTS.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            assert float(text.rstrip("%").split()[0].replace(",", "")) == pytest.approx(float(value)), text
        else:
            assert text == str(value) or text in SOURCES, f"{text}: name its source in SOURCES"


@pytest.mark.parametrize("page", sorted(PAGES))
def test_learning_pages_quote_no_number_by_hand(page):
    hand = sorted({m.group(0).strip() for m in NUMBER.finditer(prose(page))} - set(CONSTANTS))
    assert not hand, f"{page} quotes {hand} by hand: fill them from a results file (<!-- fig:value FILE PATH -->) or name the constant's source here"


def test_a_hand_copied_number_is_caught():
    text = REFERENCE.sub(" ", "SAC-TDM has 64.2 contacts, 1,204 N (Fig. 9b, eq. 3, Fig. 8/12)")
    assert [m.group(0) for m in NUMBER.finditer(text)] == ["64.2", "1,204"]
    assert not list(NUMBER.finditer(REFERENCE.sub(" ", "Fig. 11b-d and issue 51")))
