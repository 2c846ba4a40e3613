"""The README's figures are what the committed results files say (`make readme-figures` fills
them), and the filling mechanism renders, scales, formats and refuses as documented."""
import json
from pathlib import Path

import pytest

from skinsafe.core.app import readme
from skinsafe.core.app.readme import FigureError, fill, fmt, lookup

ROOT = Path(__file__).resolve().parents[2]


def test_readme_and_docs_figures_match_the_results_files():
    kinds = set()
    for page in readme.pages(ROOT):
        text = page.read_text()
        _, changed = fill(text, ROOT)
        assert not changed, f"{page}: figures differ from results/ (run `make readme-figures`):\n" + "\n".join(changed)
        kinds |= {m[0] for m in readme.MARKER.findall(text)}
    assert {"maze-grid", "safety-audit", "paper-results", "table", "value"} <= kinds


def test_every_docs_page_is_in_the_nav_and_the_readme_stays_short():
    listed = set(readme.pages(ROOT))
    on_disk = {p for p in (ROOT / "docs").rglob("*.md")}
    assert on_disk - listed == set(), f"docs pages missing from mkdocs.yml's nav: {sorted(on_disk - listed)}"
    assert all(p.is_file() for p in listed), f"nav names missing pages: {[p for p in listed if not p.is_file()]}"
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def test_a_stale_figure_is_named_and_rewritten(tmp_path):
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "r.json").write_text(json.dumps({
        "command": "skinsafe bench x", "rows": [{"n": 1024, "ms": 0.07123, "ok": True}, {"n": 16384, "ms": 1234.5}],
        "runs": {"no modulation": {"clear": [-3.39, 8.48]}}, "wall_s": 219.4}))
    text = ("Took <!-- fig:value results/r.json wall_s:mins -->3 min 39 s<!-- /fig -->, clearance "
            "<!-- fig:value results/r.json \"runs.no modulation.clear.max:+.1f\" -->+42.7<!-- /fig --> mm.\n"
            "<!-- fig:table results/r.json n,ms:.3f,ok -->\nold\n<!-- /fig -->\n"
            "```text\n<!-- fig:value results/r.json gone -->example<!-- /fig -->\n```\n")
    new, changed = fill(text, tmp_path)
    assert "Took <!-- fig:value results/r.json wall_s:mins -->3 min 39 s<!-- /fig -->" in new  # unchanged: 219 s
    assert "-->+8.5<!-- /fig --> mm" in new
    assert "| n | ms | ok |\n| ---: | ---: | --- |\n| 1,024 | 0.071 | yes |\n| 16,384 | 1,234.500 | — |" in new
    assert "example" in new  # markers in code blocks are examples
    assert len(changed) == 2 and "line 1" in changed[0] and "'+42.7' -> '+8.5'" in changed[0]
    assert fill(new, tmp_path)[1] == []
    with pytest.raises(FigureError, match=r"line 1, fig:value results/gone.json x: results file 'results/gone.json' "
                                          "is missing"):
        fill("<!-- fig:value results/gone.json x -->1<!-- /fig -->", tmp_path)
    with pytest.raises(FigureError, match="no 'nope' in 'rows.0.nope'"):
        fill("<!-- fig:value results/r.json rows.0.nope -->1<!-- /fig -->", tmp_path)
    with pytest.raises(FigureError, match="unknown figure 'fig:pie'"):
        fill("<!-- fig:pie -->\n<!-- /fig -->", tmp_path)


def test_paths_reduce_scale_and_format():
    data = {"rows": [{"f": 1.5, "n": None}, {"f": 4.0}], "s": {"slope": 0.00083, "alpha": 0.01}}
    assert lookup(data, "rows.f.max") == 4.0 and lookup(data, "rows.f.len") == 2
    assert lookup(data, "s.slope*100") == pytest.approx(0.083)
    assert lookup(data, "s.alpha*100/12") == pytest.approx(0.08333333)
    assert [fmt(v) for v in (0.07123, 93.94, 1234.5, 21000, None, False)] == ["0.0712", "93.9", "1,234", "21,000", "—", "no"]
    assert fmt(389.6, "mins") == "6 min 30 s" and fmt(0.978, ".0%") == "98%" and fmt("a b", "code") == "`a b`"
    assert fmt([-0.0123, 0.0456], "+.1%") == "[-1.2%, +4.6%]"


def test_skinsafe_readme_check_exits_1_on_a_stale_readme(tmp_path, capsys):
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "r.json").write_text('{"v": 2.0}')
    path = tmp_path / "README.md"
    path.write_text("v = <!-- fig:value results/r.json v -->1<!-- /fig -->\n")
    args = type("A", (), {"readme": str(path), "check": True})
    assert readme.run(args) == 1 and "fig:value results/r.json v: '1' -> '2'" in capsys.readouterr().err
    args.check = False
    assert readme.run(args) == 0 and path.read_text() == "v = <!-- fig:value results/r.json v -->2<!-- /fig -->\n"
    args.check = True
    assert readme.run(args) == 0


def test_the_nstep_figure_chooses_each_label_sets_step_from_its_rows(tmp_path):
    """Per label set: the 2-step TDM's rollout step is the T = 2 row with the fewest contact ticks, the grid's lowest
    is over every n-step row (`tdm2` is the configured T and step; the one-step TDM and vanilla are not in the grid)."""
    import json

    from skinsafe.core.app.readme import tracking_nstep

    def row(method, c):
        return {"method": method, "contacts_ep6_10": c, "contacts_ep6_10_ci95_low": c - 1, "contacts_ep6_10_ci95_high": c + 1,
                "onsets_ep6_10": 1.0, "onsets_ep6_10_ci95_low": 0.5, "onsets_ep6_10_ci95_high": 1.5,
                "alignment_cos_ep6_10": None, "tracking_error_mm": 50.0}

    rows = {"binary": [row("vanilla", 1.0), row("tdm", 2.0), row("tdm2", 70.0), row("tdm2@0.05s", 60.0), row("tdm3@0.05s", 30.0)],
            "soft": [row("vanilla", 1.0), row("tdm2", 5.0), row("tdm2@0.05s", 6.0), row("tdm1@0.15s", 40.0)]}
    path = tmp_path / "results/tracking/nstep_grid/tracking.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"config": {"horizon": 2, "rollout_dt": 0.15, "seeds": [0, 1, 2]},
                                "labels": {k: {"summary": v} for k, v in rows.items()}}))
    text = tracking_nstep(tmp_path)
    assert "binary: the 2-step TDM's rollout step 0.05 s (60.0 contact ticks); the grid's lowest T = 3, 0.05 s (30.0)" in text
    assert "soft: the 2-step TDM's rollout step 0.15 s (5.0 contact ticks); the grid's lowest T = 2, 0.15 s (5.0)" in text
    assert "| binary | tdm2 | 2 | 0.15 | 70.0 [69.0, 71.0] |" in text and "| soft | vanilla | — | — |" in text


def test_the_fig9_cell_says_why_the_fewest_contacts_of_each_replicate_and_their_goal_rate():
    """The paper table's Fig. 9 cell names, per replicate, the method with the fewest total contacts and whether it
    reaches the goal (the maze grid's verdict turns on methods that avoid contacts by never getting there)."""
    from skinsafe.core.app.readme import _fig9

    def rep(totals, goals):
        return {"summary": {"methods": {m: {"total_contacts_mean": t, "goal_rate_last_mean": g}
                                        for m, t, g in zip(("A", "B", "C"), totals, goals)}}}

    maze = {"claims": {"total": {"verdict": "does not hold", "replicate_verdicts": ["does not hold", "holds"]},
                       "online": None, "convergence": {}},
            "protocol": {"episodes": 60, "trials": 4}, "eval_seeds": list(range(8)),
            "replicates": [rep((900.0, 12.5, 40.0), (1.0, 0.0, 0.5)), rep((3.0, 1200.0, 8.0), (0.25, 1.0, 1.0))]}
    cell = _fig9(maze)
    assert cell.startswith("**does not hold** (replicates: does not hold, holds; 8 held-out seeds x 60 episodes")
    assert "The fewest total contacts: B 12.5 in replicate 1 (goal rate 0.00 over its last" in cell
    assert "; A 3.0 in replicate 2 (goal rate 0.25 over its last" in cell
