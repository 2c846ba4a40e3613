"""The demo report page: pictures embedded at their own size, wide tables scrolling inside the
page, numbers people can read; its plots titled and labelled with units, seed bands honest, its
tables only what was run."""
import base64
import json
import re
from pathlib import Path

import numpy as np

from skinsafe.core.app.report import Section, write_report

ROOT = Path(__file__).resolve().parents[2]

PNG = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8DwHwAFBQIAX8jx0gAAAABJRU5ErkJggg==")


def test_report_embeds_pictures_and_keeps_tables_readable(tmp_path):
    pic = tmp_path / "p.png"
    pic.write_bytes(PNG)
    rows = [{"n_taxels": 4134, "steps_per_s": 32885.4, "overhead": 0.2531, "kernel": "19 pt/taxel"}]
    path = write_report(tmp_path / "r.html", "T", "intro", [
        Section("S", "one\n\ntwo", images=[(str(pic), "a <robot>"), (str(tmp_path / "gone.png"), "x")],
                tables=[(rows, "what it means")])])
    page = path.read_text()
    assert page.count("data:image/png;base64,") == 1 and "missing picture" in page
    assert "a &lt;robot&gt;" in page  # captions escaped
    assert "<td>32,885</td>" in page and "<td>0.2531</td>" in page and "<td>4134</td>" in page
    assert re.search(r"<div class='scroll'><table>", page) and "overflow-x:auto" in page
    assert "max-width:520px" not in page  # pictures are not shrunk to half the page


# --- the report's plots (core/app/report_figures.py) and tables (core/app/demo.py) -------------------------------

UNIT = re.compile(r"\([^()]*\b(s|ms|mm|cm|m|N|rad|ratio|count|number|points|x)\b[^()]*\)")


def _numeric(ticks) -> bool:
    texts = [t.get_text().replace("\u2212", "-").replace(",", "") for t in ticks if t.get_text()]
    return bool(texts) and all(re.fullmatch(r"-?[\d.]+(e-?\d+)?|\$[^$]*\$", t) for t in texts)


def _labelled(fig) -> None:
    """Every panel titled and every axis labelled, with a unit in parentheses where its ticks are
    numbers (3-D panels: all three axes); categorical axes (merges, events) name their categories."""
    fig.canvas.draw()
    for ax in fig.axes:
        assert ax.get_title() or fig._suptitle is not None, ax
        axes = [ax.xaxis, ax.yaxis] + ([ax.zaxis] if hasattr(ax, "zaxis") else [])
        for axis in axes:
            label = axis.get_label().get_text()
            assert label, f"an unlabelled axis in '{ax.get_title()}'"
            if _numeric(axis.get_ticklabels()):
                assert UNIT.search(label), f"'{label}' names no unit ({ax.get_title()})"


def _maze(seeds: int, methods=("SAC", "SAC-TDM"), episodes=12) -> dict:
    rng = np.random.default_rng(seeds)
    runs = [{"method": m, "seed": s, "returns": rng.uniform(0, 100, episodes).tolist(),
             "costs": rng.integers(0, 40, episodes).tolist()} for m in methods for s in range(seeds)]
    return {"replicates": [{"summary": {"methods": {m: {} for m in methods}}, "runs": runs}], "eval_seeds": list(range(seeds)),
            "evaluation_conditions": {"episodes": episodes, "max_steps": 20}}


def test_maze_plot_draws_seeds_as_lines_below_three_and_bands_within_their_range(tmp_path):
    from skinsafe.core.app import report_figures as rf

    two = rf.maze(_maze(2), grid=_maze(5, ("SAC-TDM", "AC-TDM", "RRL", "CPO", "SQRL", "SAC")))
    _labelled(two)
    contacts, baselines = two.axes[1], two.axes[2]
    assert not contacts.collections and len(contacts.lines) == 4  # 2 methods x 2 seeds, no band
    assert {"RRL", "CPO", "SQRL", "SAC-TDM", "AC-TDM"} == {ln.get_label() for ln in baselines.lines}
    assert "5 seeds x 12 episodes" in baselines.get_title()
    five = _maze(5)
    fig = rf.maze(five)
    for ax, key in ((fig.axes[0], "returns"), (fig.axes[1], "costs")):
        for band in ax.collections:  # every band inside what the seeds span (contacts never below 0)
            lo = band.get_paths()[0].vertices[:, 1].min()
            assert lo >= min(min(r[key]) for r in five["replicates"][0]["runs"]) - 1e-9 and lo >= 0
    assert rf.save(fig, tmp_path / "m.png").stat().st_size > 10_000


def test_results_plots_are_labelled_with_units():
    from skinsafe.core.app import report_figures as rf

    root = ROOT / "results"
    tracking = json.loads((root / "tracking" / "reduced" / "tracking.json").read_text())
    poke = json.loads((root / "poke" / "poke_results.json").read_text())
    for fig in (rf.tracking_contacts(tracking), rf.tracking_paths(tracking), rf.poke_force(poke),
                rf.poke_multicontact(poke), rf.desk(json.loads((root / "desk" / "desk.json").read_text())),
                rf.collaboration(json.loads((root / "collaboration" / "collaboration.json").read_text()))):
        _labelled(fig)
    paths = rf.tracking_paths(tracking)
    assert all(ax.get_zlabel() == "z (m)" for ax in paths.axes)


def test_tables_show_what_was_run_and_say_why_a_value_is_missing():
    from skinsafe.core.app.demo import safety_row, tracking_rows

    run = json.loads((ROOT / "results" / "tracking" / "reduced" / "tracking.json").read_text())
    run["config"]["episodes"] = 10
    assert "contacts_ep6_10" in tracking_rows(run)[0]  # a run of 10 episodes
    run["config"]["episodes"] = 3
    row = tracking_rows(run)[0]
    assert not any("ep6_10" in k for k in row) and "contacts_last (episode 3)" in row
    assert safety_row({"cases": 20, "dominant_ratio_min": None})["dominant_ratio_min"] == \
        "not measured: no tick left the dominant contact free in 20 cases"
    assert safety_row({"cases": 20, "dominant_ratio_min": 1.0})["dominant_ratio_min"] == 1.0
