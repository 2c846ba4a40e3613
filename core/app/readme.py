"""`skinsafe readme`: the figures quoted in README.md and the docs pages, filled in from the results files
the code writes.

A figure sits between two HTML comments, which Markdown does not show:

    <!-- fig:value FILE KEY.PATH[:FORMAT] -->0.0830<!-- /fig -->      one number in a sentence
    <!-- fig:table FILE COLUMN[:FORMAT],... [where=KEY=VALUE,...] -->   a table of a file's rows
    | ... |
    <!-- /fig -->
    <!-- fig:const MODULE NAME.ATTR[:FORMAT] -->0.05<!-- /fig -->        a constant or default of the code
    <!-- fig:NAME -->...<!-- /fig -->                                   a composite figure (FIGURES below)

Arguments are split as a shell would (quote a path with spaces: `"runs.no modulation.peak"`).
FILE is relative to the repository (a `results/...` JSON); KEY.PATH walks its dicts and lists
(`summary.claim.holds`, `runs.0.seconds`, `fail_open.sum`: a key of every row of a list), reduces a
list (`force.max`: min, max, sum, mean, len)
and scales (`slope*100`, `params.alpha*100/12`); a table's rows are the file itself when it is a list,
or its `rows`. FORMAT is a Python format spec (`.3f`, `+.1f`, `.0%`), `mins` (seconds as "3 min 39 s") or
`code` (as inline code: a command), each item of a list (an interval: `[-1.2%, +3.4%]`); without one, numbers keep 3 significant digits and thousands get separators.

Markers inside fenced code blocks are examples, left alone. `skinsafe readme` rewrites README.md and every
page of mkdocs.yml's nav (`pages`); `--check` changes nothing and exits 1 naming every figure whose text is
not what its results file says (tests/app/test_readme_figures.py runs it).
"""
from __future__ import annotations

import json
import math
import re
import shlex
import sys
from pathlib import Path

from skinsafe.core.skin.files import atomic_write

REPO = Path(__file__).resolve().parents[2]
MARKER = re.compile(r"<!-- fig:(\S+)((?: [^>]*?)?) -->(.*?)<!-- /fig -->", re.S)
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


class FigureError(ValueError):
    """A figure marker that cannot be filled: names the marker and what to do."""


def load(root: Path, file: str):
    path = root / file
    if not path.is_file():
        raise FigureError(f"results file '{file}' is missing; run the command that writes it (README names it)")
    return json.loads(path.read_text())


REDUCE = {"min": min, "max": max, "sum": sum, "len": len, "mean": lambda v: sum(v) / len(v)}


def lookup(data, path: str):
    """The value at KEY.PATH (module doc): keys, list indices, a key of every row of a list, `min`,
    `max`, `sum`, `mean` (of its values that are not null), `len` of a list; a trailing `*F` or `/F` (repeatable) scales a number."""
    path, *ops = re.split(r"(?=[*/][0-9.])", path)
    for key in path.split("."):
        try:
            if isinstance(data, list) and key in REDUCE:  # a missing value (null: nothing measured) left out
                data = REDUCE[key](data if key == "len" else [v for v in data if v is not None])
            elif isinstance(data, list) and not key.lstrip("-").isdigit():  # a key of every row
                data = [row[key] for row in data]
            else:
                data = data[int(key)] if isinstance(data, list) else data[key]
        except (KeyError, IndexError, ValueError, TypeError):
            raise FigureError(f"no '{key}' in '{path}'") from None
    for op in ops:
        data = data * float(op[1:]) if op[0] == "*" else data / float(op[1:])
    return data


def constant(module: str, path: str):
    """The value at NAME.ATTR... in a module of the code (a constant, a dataclass's default; in a dict, list or
    numpy array as `lookup` walks and reduces them), scaled as `lookup` scales: the docs quote the code's own
    settings, never a copy of them."""
    import importlib

    path, *ops = re.split(r"(?=[*/][0-9.])", path)
    try:
        data = importlib.import_module(module)
    except ImportError as e:
        raise FigureError(f"no module '{module}' ({e})") from None
    keys = path.split(".")
    for i, key in enumerate(keys):
        data = data.tolist() if hasattr(data, "tolist") else list(data) if isinstance(data, tuple) else data  # a
        # numpy array or a tuple: a list, walked and reduced as lookup does
        if isinstance(data, (dict, list)):
            return lookup(data, ".".join(keys[i:]) + "".join(ops))
        try:
            data = getattr(data, key)
        except AttributeError:
            raise FigureError(f"no '{key}' in '{module}.{path}'") from None
    return lookup({"v": data.tolist() if hasattr(data, "tolist") else data}, "v" + "".join(ops))


def fmt(v, spec: str = "") -> str:
    """A value as the README prints it (module doc); None as a dash, booleans as yes/no."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, list):  # e.g. an interval
        return "[" + ", ".join(fmt(x, spec) for x in v) + "]"
    if spec == "code":
        return f"`{v}`"
    if isinstance(v, (int, float)) and spec == "mins":
        m, s = divmod(int(round(v)), 60)
        return f"{m} min {s} s" if m else f"{s} s"
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if spec:
        if isinstance(v, (int, float)) and abs(v) >= 1000 and "," not in spec and spec[-1] in "fdg":
            spec = "," + spec
        return format(v, spec)
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"
    return str(v)


def _columns(spec: str) -> list[tuple[str, str]]:
    return [tuple(c.split(":", 1)) if ":" in c else (c, "") for c in spec.split(",") if c]


def table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    """A Markdown table of `rows`, one column per (key, format); numbers right-aligned."""
    if not rows:
        raise FigureError("no rows")
    for key, _ in columns:
        if all(key not in r for r in rows):
            raise FigureError(f"no row has '{key}' (keys: {sorted({k for r in rows for k in r})})")
    numeric = [all(r.get(k) is None or isinstance(r.get(k), (int, float)) and not isinstance(r.get(k), bool)
                   for r in rows) for k, _ in columns]
    lines = ["| " + " | ".join(k for k, _ in columns) + " |",
             "| " + " | ".join("---:" if n else "---" for n in numeric) + " |"]
    lines += ["| " + " | ".join(fmt(r.get(k), f) for k, f in columns) + " |" for r in rows]
    return "\n".join(lines)


def _rows(data) -> list[dict]:
    rows = data.get("rows") if isinstance(data, dict) else data
    if not isinstance(rows, list):
        raise FigureError("the file holds no rows (a list, or a dict with 'rows')")
    return rows


def _where(rows: list[dict], spec: str) -> list[dict]:
    for cond in filter(None, spec.split(",")):
        key, _, want = cond.partition("=")
        rows = [r for r in rows if str(r.get(key)) == want]
    return rows


def render(kind: str, args: list[str], root: Path) -> str:
    """The text of one figure marker."""
    if kind == "value":
        if len(args) != 2:
            raise FigureError("use <!-- fig:value FILE KEY.PATH[:FORMAT] -->")
        path, _, spec = args[1].partition(":")
        return fmt(lookup(load(root, args[0]), path), spec)
    if kind == "const":
        if len(args) != 2:
            raise FigureError("use <!-- fig:const MODULE NAME.ATTR[:FORMAT] -->")
        path, _, spec = args[1].partition(":")
        return fmt(constant(args[0], path), spec)
    if kind == "table":
        if len(args) not in (2, 3) or (len(args) == 3 and not args[2].startswith("where=")):
            raise FigureError("use <!-- fig:table FILE COLUMN[:FORMAT],... [where=KEY=VALUE,...] -->")
        rows = _rows(load(root, args[0]))
        if len(args) == 3:
            rows = _where(rows, args[2][len("where="):])
        return "\n" + table(rows, _columns(args[1])) + "\n"
    if kind in FIGURES:
        if len(args) > (1 if kind in GRIDS else 0):
            raise FigureError(f"fig:{kind} takes " + ("at most a results file" if kind in GRIDS else "no arguments"))
        return "\n" + FIGURES[kind](root, *args) + "\n"
    raise FigureError(f"unknown figure 'fig:{kind}'; use value, table, const or one of {sorted(FIGURES)}")


def fill(text: str, root: Path = REPO) -> tuple[str, list[str]]:
    """`text` with every figure re-rendered, and one line per figure whose text changed."""
    changed = []
    fences = [f.span() for f in FENCE.finditer(text)]

    def sub(m: re.Match) -> str:
        if any(a <= m.start() < b for a, b in fences):  # an example in a code block, not a figure
            return m.group(0)
        kind, args, old = m.group(1), shlex.split(m.group(2)), m.group(3)
        line = text.count("\n", 0, m.start()) + 1
        try:
            new = render(kind, args, root)
        except FigureError as e:
            raise FigureError(f"line {line}, fig:{kind} {' '.join(args)}: {e}") from None
        if new != old:
            changed.append(f"line {line}: fig:{kind} {' '.join(args)}: {_short(old)} -> {_short(new)}")
        return m.group(0).replace(f"-->{old}<!--", f"-->{new}<!--", 1)

    return MARKER.sub(sub, text), changed


def _short(s: str) -> str:
    s = " ".join(s.split())
    return repr(s if len(s) < 60 else s[:57] + "...")


# --- composite figures: the README's tables that combine several results files -------------------


def _chosen(rep: dict, method: str) -> str:
    """The configuration a replicate evaluated: tuning's trial, or its defaults where no trial met the criterion."""
    from skinsafe.core.experiments.maze_report import config_text

    t = rep["tuning"].get(method)
    conf = config_text({k: v for k, v in rep["chosen"][method].items() if k != "cost_limit"})
    if t is None:
        return f"defaults: {conf}"
    if not t["met_criterion"]:
        return f"no trial of {t['trials']} met the goal criterion: defaults ({conf})"
    return f"trial {t['chosen_index']} of {t['trials']}: {conf}"


MAZE, TRACKING = "results/maze/maze_results.json", "results/tracking/tracking.json"


def maze_grid(root: Path, file: str = MAZE) -> str:
    """The maze grid (`file`: the full grid's, or a reduced run's), one table per replicate (its tuning seeds, its
    verdicts): per method total contacts on the held-out seeds (mean and 95% interval as computed, online /
    offline, per seed), goal rates, the configuration its tuning chose."""
    from skinsafe.core.experiments.verdicts import phrase

    data = load(root, file)
    seeds = data["eval_seeds"]
    out = []
    for k, rep in enumerate(data["replicates"]):
        sm = rep["summary"]
        tdm = {m for m in sm["methods"] if m.endswith("-TDM")}
        verdict = sm["claim"]["verdict"] if sm["claim"] else "—"
        online = f"; online contacts only: {sm['claim_online']['verdict']}" if sm["claim_online"] else ""
        out += [f"**Replicate {k + 1}** (tuning seeds {', '.join(map(str, rep['tuning_seeds'])) or 'none'}): the claim "
                f"{phrase(verdict)}{online}.", "",
                f"| method | total contacts, mean [95% CI] over seeds {seeds[0]}-{seeds[-1]} | online / offline | per seed (total) "
                "| goal rate, last 20 episodes (seeds >= 0.8) | configuration |", "| --- | ---: | ---: | --- | --- | --- |"]
        for m, v in sm["methods"].items():
            mine = sorted((r for r in rep["per_seed"] if r["method"] == m), key=lambda r: r["seed"])
            lo, hi = v["total_contacts_ci95"]
            cell = f"{v['total_contacts_mean']:,.1f} [{lo:,.1f}, {hi:,.1f}]"
            out.append(f"| {'**' + m + '**' if m in tdm else m} | {'**' + cell + '**' if m in tdm else cell} | "
                       f"{v['online_contacts_mean']:,.1f} / {v['offline_contacts_mean']:,.1f} | "
                       f"{' / '.join(fmt(int(r['total_contacts'])) for r in mine)} | {v['goal_rate_last_mean']:.2f} "
                       f"({v['seeds_reaching']}/{v['seeds']}) | {_chosen(rep, m)} |")
        out.append("")
    return "\n".join(out).rstrip()


def maze_defaults(root: Path) -> str:
    """Every maze method's trial 0, its search space and where its defaults come from (`maze.SPACES`,
    `maze.DEFAULTS_SOURCE`: the code the experiment runs)."""
    from skinsafe.core.experiments.maze import DEFAULTS_SOURCE, SPACES

    def space(values) -> str:
        return " / ".join(map(str, values)) if isinstance(values, list) else f"{values[0]} {values[1]:g} to {values[2]:g}"

    lines = ["| method | trial 0 (defaults) | search space | source of the defaults |", "| --- | --- | --- | --- |"]
    for m, sp in SPACES.items():
        lines.append(f"| {m} | {', '.join(f'{k} {d:.3g}' if isinstance(d, float) else f'{k} {d}' for k, (d, _) in sp.items())} | "
                     f"{'; '.join(f'{k} {space(v)}' for k, (_, v) in sp.items())} | {DEFAULTS_SOURCE[m]} |")
    return "\n".join(lines)


def safety_audit(root: Path) -> str:
    """`skinsafe bench safety`'s rows, limits and counts side by side (related counts share a cell)."""
    rows = load(root, "results/safety/safety_audit.json")
    lines = ["| robot | contacts | cases (feasible / infeasible) | into_contact_mm_worst (all cases) | "
             "dominant_ratio_min (cases) | vel / acc limit violations, nonfinite / missing cases | fail_open / solver_failed | "
             "ms median / p99.9 / worst |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        ratio = "—" if r.get("dominant_ratio_min") is None else f"{r['dominant_ratio_min']:.3f}"
        lines.append(
            f"| {r['robot']} | {r['contacts']} | {fmt(r['cases'])} ({fmt(r['feasible'])} / {_opt(r, 'infeasible_cases', ',')}) | "
            f"{r['into_contact_mm_worst']:.3f} ({_opt(r, 'into_contact_mm_worst_all', '.3f')}) | "
            f"{ratio} ({fmt(r['dominant_cases'])}) | "
            f"{r['vel_limit_violations']} / {r['acc_limit_violations']}, {r['nonfinite_cases']} / "
            f"{_opt(r, 'missing_cases', ',')} | {r['fail_open']} / {r.get('solver_failed', '—')} | "
            f"{r['ms_median']:.2f} / {r['ms_p999']:.1f} / {r['ms_worst']:.0f} |")
    return "\n".join(lines)


def tracking_labels(root: Path, file: str = TRACKING) -> str:
    """Fig. 11 per label set (the headline first) and replicate: contact ticks over episodes 6-10 (mean and 95%
    interval over seeds, per seed), onsets, the potential's alignment and tracking error."""
    track = load(root, file)
    lines = ["| labels | replicate (seeds) | method | contact ticks, episodes 6-10, mean [95% CI] | per seed | "
             "onsets, episodes 6-10 [95% CI] | cos(n, -grad d) before the balls | tracking error mm |",
             "| --- | --- | --- | ---: | --- | ---: | ---: | ---: |"]
    for labels, res in track["labels"].items():
        for k, rep in enumerate(res["replicates"]):
            per = {(r["method"], r["seed"]): r for r in rep["per_seed"]}
            for r in rep["summary"]:
                seeds = " / ".join(f"{per[(r['method'], sd)]['contacts_ep6_10']:.1f}" for sd in rep["seeds"] if (r["method"], sd) in per)
                align = "—" if r["alignment_cos_ep6_10"] is None else f"{r['alignment_cos_ep6_10']:+.2f}"
                lines.append(f"| {labels} ({res['role']}) | {k + 1} ({rep['seeds'][0]}-{rep['seeds'][-1]}) | {r['method']} | "
                             f"{r['contacts_ep6_10']:.1f} [{r['contacts_ep6_10_ci95_low']:.1f}, "
                             f"{r['contacts_ep6_10_ci95_high']:.1f}] | {seeds} | {r['onsets_ep6_10']:.1f} "
                             f"[{r['onsets_ep6_10_ci95_low']:.1f}, {r['onsets_ep6_10_ci95_high']:.1f}] | {align} | "
                             f"{r['tracking_error_mm']:.0f} |")
    return "\n".join(lines)


def tracking_claims(root: Path, file: str = TRACKING) -> str:
    """Per label set what its labels use and its verdict, settled across its replicates, in contact ticks
    (Fig. 11e's count) and in onsets; per replicate each comparison with its Holm-adjusted p-value."""
    from skinsafe.core.experiments.tracking_report import claim_statement, label_set_statement

    track = load(root, file)
    out = []
    for name, res in track["labels"].items():
        out += [f"- **{name}** ({res['uses']}): {label_set_statement(res)}"]
        out += [f"    - replicate {k + 1}: {claim_statement(rep['claim'])}" for k, rep in enumerate(res["replicates"]) if rep["claim"]]
    return "\n".join(out)


NSTEP = re.compile(r"tdm(\d+)@([0-9.]+)s")


def tracking_nstep(root: Path) -> str:
    """The n-step grid on the tuning seeds (`--horizons`, `--rollout-dts`), each label set alike: every (T, rollout
    step) with its contact ticks, onsets and alignment, then per label set the 2-step TDM's rollout step chosen by
    the lowest contact ticks over episodes 6-10, and the lowest setting of the whole grid."""
    track = load(root, "results/tracking/nstep_grid/tracking.json")
    cfg = track["config"]
    lines = ["| labels | method | T | rollout step s | contact ticks, episodes 6-10 [95% CI] | onsets [95% CI] | "
             "cos(n, -grad d) | tracking error mm |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    chosen = []
    for labels, res in track["labels"].items():
        grid = []
        for r in res["summary"]:
            m = NSTEP.fullmatch(r["method"])
            T, dt = (int(m[1]), float(m[2])) if m else (cfg["horizon"], cfg["rollout_dt"]) if r["method"] == "tdm2" else (None, None)
            if T is not None:
                grid.append((r["contacts_ep6_10"], T, dt))
            align = "—" if r["alignment_cos_ep6_10"] is None else f"{r['alignment_cos_ep6_10']:+.2f}"
            lines.append(f"| {labels} | {r['method']} | {T or '—'} | {'—' if dt is None else f'{dt:g}'} | "
                         f"{r['contacts_ep6_10']:.1f} [{r['contacts_ep6_10_ci95_low']:.1f}, {r['contacts_ep6_10_ci95_high']:.1f}] | "
                         f"{r['onsets_ep6_10']:.1f} [{r['onsets_ep6_10_ci95_low']:.1f}, {r['onsets_ep6_10_ci95_high']:.1f}] | "
                         f"{align} | {r['tracking_error_mm']:.0f} |")
        two = min((g for g in grid if g[1] == 2), default=None)
        best = min(grid, default=None)
        if two and best:
            chosen.append(f"{labels}: the 2-step TDM's rollout step {two[2]:g} s ({two[0]:.1f} contact ticks); the grid's lowest "
                          f"T = {best[1]}, {best[2]:g} s ({best[0]:.1f})")
    seeds = ", ".join(map(str, cfg["seeds"]))
    return "\n".join(lines) + f"\n\nChosen on seeds {seeds} (lowest contact ticks over episodes 6-10): " + "; ".join(chosen) + "."


def _grid(root: Path, file: str) -> dict | None:
    """A full grid's result, or None while its grid is not complete (the file is written at the end)."""
    return load(root, file) if (root / file).is_file() else None


def _pending(name: str) -> str:
    """The cell of a claim whose full grid is not complete: what to run (it resumes from the finished runs)."""
    return (f"**not computed yet** under the current protocol: `nice skinsafe experiment {name}` writes it (a stopped run "
            f"resumes from the finished runs in results/{name}/tasks)")


def _fig9(maze: dict) -> str:
    """Fig. 9's cell: the verdict settled across the replicates and the protocol in a sentence; each replicate's
    totals and comparisons are the Strategy page's maze grid and `maze_results.json`'s `claims`."""
    from skinsafe.core.experiments.maze_claims import LAST
    from skinsafe.core.experiments.maze_report import FASTER

    cl, proto = maze["claims"], maze["protocol"]
    online = f"; online contacts only: {cl['online']['verdict']}" if cl["online"] else ""
    conv = "".join(f"; Fig. 9c {k}: {FASTER.get(v['verdict'], v['verdict'])}" for k, v in cl["convergence"].items())
    fewest = []  # why: the fewest total contacts of each replicate, and whether that method reaches the goal
    for i, rep in enumerate(maze["replicates"]):
        m, s = min(rep["summary"]["methods"].items(), key=lambda kv: kv[1]["total_contacts_mean"])
        fewest.append(f"{m} {s['total_contacts_mean']:,.1f} in replicate {i + 1} (goal rate {s['goal_rate_last_mean']:.2f} over "
                      f"its last {LAST} episodes)")
    return (f"**{cl['total']['verdict']}** (replicates: {', '.join(cl['total']['replicate_verdicts'])}; "
            f"{len(maze['eval_seeds'])} held-out seeds x {proto['episodes']} episodes, {proto['trials']} Optuna trials "
            f"per method, Holm-corrected Welch tests{online}{conv}). The fewest total contacts: {'; '.join(fewest)}. "
            "Each replicate's totals and tests: "
            "[Strategy](../simulate/strategy.md#results), `maze_results.json` `claims`")


def _fig11(track: dict) -> str:
    """Fig. 11's cell: the headline's verdict settled across its replicates (ticks, onsets), the 2-step TDM's
    share of vanilla's contacts per replicate, each extension's verdict; each comparison is the Modulation
    page's claims table and `tracking.json`."""
    from skinsafe.core.experiments.tracking import SHARE

    head = track["labels"][track["headline"]]
    shares = ", ".join(f"{rep['claim']['tdm2_over_vanilla']:.0%}" for rep in head["replicates"])
    ext = "".join(f"; extension {name}: {res['settled']['verdict']}"
                  for name, res in track["labels"].items() if res["role"] == "extension")
    return (f"**{head['settled']['verdict']}** with the paper's labels ({len(head['replicates'])} replicates of "
            f"{len(head['replicates'][0]['seeds'])} held-out seeds x {track['config']['episodes']} episodes, "
            f"{fmt(track['n_taxels'])} taxels; contacts counted in ticks as Fig. 11e): 2-step / vanilla {shares} "
            f"(claimed at most {SHARE:.0%}); in contact onsets {head['settled_onsets']['verdict']}{ext}. Each "
            "comparison: [Modulation](../simulate/modulation.md#results-on-held-out-seeds), `tracking.json`")


def _opt(row: dict, key: str, spec: str) -> str:
    """A row's value formatted, or a dash where the row predates the key."""
    return "—" if row.get(key) is None else format(row[key], spec)


def _fig7(poke: dict) -> str:
    rows = [r for r in poke["multicontact"] if r["contacts"] == 2]
    qp = next(r for r in rows if r["merge"] == "qp")
    ratio = lambda r: f"{r['dominant_fraction']:.2f} / {sum(r['others_fraction']) / len(r['others_fraction']):.2f}"  # noqa: E731
    closed = "; ".join(f"{r['merge']} ε = {r['epsilon']:g} {ratio(r)} ({r['into_contact_mm']:.1f} mm into contact)"
                       for r in rows if r["merge"] != "qp")
    return (f"prioritised QP, 2 contacts: dominant {qp['dominant_fraction']:.2f} of its own distance, the other "
            f"{ratio(qp).split(' / ')[1]} (eq. 12 re-ranks them as they retract), {qp['into_contact_mm']:.1f} mm into "
            f"its contact; closed forms: {closed}. Over random contact sets only the QP keeps every contacted taxel "
            "out (`skinsafe bench safety`)")


def paper_results(root: Path) -> str:
    """The paper's claims against ours, each figure from its results file."""
    poke = load(root, "results/poke/poke_results.json")
    maze, track = _grid(root, MAZE), _grid(root, TRACKING)
    desk = load(root, "results/desk/desk.json")
    collab = load(root, COLLAB)
    fs, alpha = poke["force_sweep"], poke["params"]["alpha"]
    forms = poke["forms"]
    touches = [r["touch_N"] for r in desk["sweep"]]
    desk_cells = ", ".join(f"{r['stack']}: {r['min_clearance_mm']:+.1f} mm ({fmt(r['desk_force_N'])} N on the desk)"
                           for r in desk["sweep_worst"])
    rows = [
        ("Fig. 8/12", "heavier touch, further retraction; −z follows eq. 10",
         f"linear, {fs['slope'] * 100:.4f} cm/N vs α/12 = {alpha / 12 * 100:.4f}, R² = {fs['r2']:.5f}; displacement "
         f"within {max(fs['profile_rel_err']) * 100:.1f}% of eq. 10", "`skinsafe poke --out results/poke`"),
        ("Fig. 7", "lower priorities interfere minimally with the dominant retraction", _fig7(poke),
         "`skinsafe poke --out results/poke`"),
        ("III-C", "6-D task (zero rotation)",
         f"the 6-D task achieves a median {forms['6d']['achieved_median']:.0%} of the commanded −z distance, a 3-D "
         f"task {forms['3d']['achieved_median']:.0%}: we default to 3-D", "`skinsafe poke --out results/poke`"),
        ("Fig. 9", "-TDM variants have the lowest total collisions", _fig9(maze) if maze else _pending("maze"),
         "`skinsafe experiment maze`"),
        ("Fig. 11", "vanilla most contacts; TDM reduces but doesn't improve; 2-step ≈ 0 after 6 episodes",
         _fig11(track) if track else _pending("tracking"), "`skinsafe experiment tracking`"),
        ("Fig. 14", "modulation stops the retraction before the desk", f"worst min clearance over touches of {fmt(min(touches))}-{fmt(max(touches))} N"
         + (f" ({desk['labels']} labels, tangent gain {desk['tangent_gain']:g})" if "labels" in desk else "") + f": {desk_cells}",
         "`skinsafe experiment desk`"),
        ("Fig. 15", "the robot retracts from an accidental contact", _fig15(collab),
         "`skinsafe experiment collaboration`"),
    ]
    lines = ["| paper | claim | ours | command |", "| --- | --- | --- | --- |"]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    return "\n".join(lines)


COLLAB = "results/collaboration/collaboration.json"


def _fig15(collab: dict) -> str:
    """The collaboration scene's worst ratio to the ISO/TS 15066 limits per scenario and stack, and
    the sweep's robot-driven cells that full+pfl exceeds."""
    per = {}
    for key, r in collab["runs"].items():
        scenario, stack = key.split("/")
        per.setdefault(scenario, []).append(f"{stack} {r['worst_ratio']:.2f}")
    over = [r for r in collab["sweep"] if r["stack"] == "full+pfl" and r["worst_ratio"] > 1
            and r["scenario"] != "person"]
    cells = len([r for r in collab["sweep"] if r["stack"] == "full+pfl" and r["scenario"] != "person"])
    sweep = (f"; sweep: full+pfl over its limit in {len(over)} of {cells} robot-driven cells"
             + (f" (worst {max(r['worst_ratio'] for r in over):.2f})" if over else "")) if cells else ""
    return ("a compliant person (ISO/TS 15066 masses, springs, force and pressure limits); worst peak over its "
            "limit per stack: " + "; ".join(f"{s}: {', '.join(v)}" for s, v in per.items()) + sweep)


def collaboration(root: Path) -> str:
    """The collaboration scene's nominal runs (collaboration.md's first table)."""
    from skinsafe.core.experiments.collaboration_result import nominal_table

    return nominal_table(load(root, COLLAB))


def collaboration_sweep(root: Path) -> str:
    """The collaboration scene's robustness sweep (collaboration.md's second table)."""
    from skinsafe.core.experiments.collaboration_result import sweep_table

    return sweep_table(load(root, COLLAB))


def sample_skins(root: Path) -> str:
    """The sample skins the docs use: the built-in robots' made now as `skinsafe sample` makes them, the
    collaboration scene's from its results file."""
    from skinsafe.core.design.sample import make_sample_design

    lines = ["| skin | made by | modules | taxels | boards |", "| --- | --- | ---: | ---: | ---: |"]
    for robot in ("ur5", "panda"):
        d = make_sample_design(robot)
        lines.append(f"| {robot.upper() if robot == 'ur5' else robot.title()} sample | `skinsafe sample --robot {robot}` | "
                     f"{fmt(len(d.modules))} | {fmt(d.n_taxels)} | {fmt(len(d.boards))} |")
    c = load(root, "results/collaboration/collaboration.json")
    lines.append(f"| collaboration | `skinsafe experiment collaboration`: the UR5 sample plus modules where a person's "
                 f"hand reaches | {fmt(c['skin_modules'])} | {fmt(c['skin_taxels'])} | — |")
    return "\n".join(lines)


def import_contracts(root: Path) -> str:
    """The import-linter contracts of pyproject.toml (what `lint-imports` checks), one row each."""
    import tomllib

    contracts = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    lines = ["| contract | kind | what it names |", "| --- | --- | --- |"]
    for c in contracts:
        names = c.get("layers") or c.get("source_modules") or c.get("ancestors") or []
        code = [", ".join(f"`{m}`" for m in n.replace("skinsafe.", "").split(" | ")) for n in names]
        what = "top to bottom: " + " -> ".join(code) if c["type"] == "layers" else ", ".join(code)
        if "forbidden_modules" in c:
            what += " never import " + ", ".join(f"`{m.replace('skinsafe.', '')}`" for m in c["forbidden_modules"])
        lines.append(f"| {c['name']} | {c['type']} | {what} |")
    return "\n".join(lines)


def hardware_constants(root: Path) -> str:
    """The sensing chain's numbers as the code states them: the FSR model both the simulation and the boards'
    readings go through, a board's channels, the link, a module's connector."""
    import inspect
    from dataclasses import fields

    from skinsafe.core.sim.sensor_model import FSRModel
    from skinsafe.core.skin.model import Board
    from skinsafe.exporters.fab import PIN_PITCH_MM
    from skinsafe.hardware.client import BoardClient
    from skinsafe.hardware.emulated_board import BoardSpec

    fsr = FSRModel()
    what = {"r_1n": "FSR resistance at 1 N (ohm)", "alpha": "power-law exponent of R(F)",
            "r_m": "divider resistor (ohm)", "r_min": "FSR resistance at saturation (ohm)",
            "f_on": "turn-on force: below it the FSR reads 0 (N)", "bits": "ADC resolution (bits)",
            "noise_counts": "ADC noise, standard deviation (counts)", "rate_hz": "a board's sample rate (Hz)",
            "latency_s": "sampling to the host having the value (s)"}
    rows = [(f"`FSRModel.{f.name}`", what[f.name], getattr(fsr, f.name)) for f in fields(fsr)]
    rows += [("`Board.capacity`", "channels of a board (default)", Board.__dataclass_fields__["capacity"].default),
             ("`BoardClient(baud=)`", "serial link speed (bit/s, `--baud`)",
              inspect.signature(BoardClient).parameters["baud"].default),
             ("`BoardSpec.max_chunk`", "the emulated board's config chunk (bytes)",
              BoardSpec.__dataclass_fields__["max_chunk"].default),
             ("`PIN_PITCH_MM`", "a module's FPC connector pitch (mm)", PIN_PITCH_MM)]
    lines = ["| name in the code | what | value |", "| --- | --- | ---: |"]
    lines += [f"| {name} | {text} | {fmt(value)} |" for name, text, value in rows]
    return "\n".join(lines)


def fault_table(root: Path) -> str:
    """The safety monitor's fault table for the sim's defaults on the UR5 sample skin (`python -m
    skinsafe.core.runtime.monitor`)."""
    from skinsafe.core.runtime.monitor import sim_defaults_table

    return sim_defaults_table()[1]


def iso_limits(root: Path) -> str:
    """ISO/TS 15066 Annex A's limits per body region as the code holds them (core/sim/body_regions.py `REGIONS`)."""
    from skinsafe.core.sim.body_regions import REGIONS

    lines = ["| region | quasi-static N | transient N | quasi-static N/cm^2 | m_H kg | k N/mm |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r.label} | {fmt(r.quasi_static_N)} | {'none' if r.transient_N is None else fmt(r.transient_N)} | "
              f"{fmt(r.pressure_N_cm2)} | {fmt(r.mass_kg)} | {fmt(r.k_N_per_m / 1e3)} |" for r in REGIONS.values()]
    return "\n".join(lines)


GRIDS = {"maze-grid", "tracking-labels", "tracking-claims"}  # figures that take a results file (default: the full grid's)
def exit_codes(root: Path) -> str:
    """`skinsafe run`'s exit codes as the command states them (core/app/run.py `EXIT_CODES`)."""
    from skinsafe.core.app.run import EXIT_CODES

    return "\n".join(["| code | meaning |", "| ---: | --- |"] + [f"| {k} | {v} |" for k, v in EXIT_CODES.items()])


def commands(root: Path) -> str:
    """Every `skinsafe` command, experiment and bench with its one line of help, as the command line lists them
    (core/app/cli.py `COMMANDS`, `EXPERIMENTS`, `BENCHES`)."""
    from skinsafe.core.app.cli import BENCHES, COMMANDS, EXPERIMENTS

    lines = ["| command | what it does |", "| --- | --- |"]
    for prefix, table in [("", COMMANDS), ("experiment ", EXPERIMENTS), ("bench ", BENCHES)]:
        lines += [f"| [`skinsafe {prefix}{name}`](#skinsafe-{(prefix + name).replace(' ', '-')}) | {text} |"
                  for name, (_, text) in table.items()]
    return "\n".join(lines)


FIGURES = {"maze-grid": maze_grid, "maze-defaults": maze_defaults, "tracking-labels": tracking_labels,
           "tracking-claims": tracking_claims, "tracking-nstep": tracking_nstep, "safety-audit": safety_audit, "paper-results": paper_results,
           "collaboration": collaboration, "collaboration-sweep": collaboration_sweep, "sample-skins": sample_skins,
           "import-contracts": import_contracts, "hardware-constants": hardware_constants,
           "fault-table": fault_table, "iso-limits": iso_limits,
           "exit-codes": exit_codes, "commands": commands}


def _nav_files(nav) -> list[str]:
    out = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        out += _nav_files(value) if isinstance(value, list) else [value]
    return out


def pages(root: Path = REPO) -> list[Path]:
    """README.md, then every docs page in the order of mkdocs.yml's nav (the order their commands run in)."""
    import yaml

    class Loader(yaml.SafeLoader):  # mkdocs.yml names Python objects (`!!python/name:`): not needed here
        pass

    Loader.add_multi_constructor("tag:yaml.org,2002:python/", lambda loader, suffix, node: None)
    Loader.add_constructor("!relative", lambda loader, node: None)
    config = yaml.load((root / "mkdocs.yml").read_text(), Loader=Loader)
    docs = root / config.get("docs_dir", "docs")
    return [root / "README.md"] + [docs / f for f in _nav_files(config["nav"])]


def add_arguments(p) -> None:
    p.add_argument("--readme", help="one page to fill (default: README.md and every docs page in mkdocs.yml)")
    p.add_argument("--check", action="store_true", help="change nothing; exit 1 if a figure differs from its results")


def run(args) -> int:
    files = [(Path(args.readme), Path(args.readme).resolve().parent)] if args.readme else \
        [(path, REPO) for path in pages()]
    stale, total, updates = 0, 0, {}
    for path, root in files:
        text = path.read_text()
        try:
            new, changed = fill(text, root)
        except FigureError as e:
            print(f"skinsafe readme: error: {path}: {e}", file=sys.stderr)
            return 2
        for line in changed:
            print(f"{path}: {line}", file=sys.stderr if args.check else sys.stdout)
        stale += len(changed)
        total += len(MARKER.findall(text))
        if changed:
            updates[path] = new
    if args.check:
        return 1 if stale else 0
    for path, new in updates.items():
        atomic_write(path, new)
    print(f"{len(files)} pages: {total} figures, {stale} updated")
    return 0
