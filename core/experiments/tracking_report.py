"""The tracking experiment's report: its verdicts in English, `tracking.md`'s tables and the figures
(`contacts.png`: Fig. 11e per label set; `trajectories.png`: Fig. 11b-d). Numbers come from the records of
`tracking` (`document`); nothing here decides a verdict."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from skinsafe.core.experiments.tracking import COUNTS
from skinsafe.core.experiments.verdicts import phrase
from skinsafe.core.skin.files import write_png

NAMES = {"vanilla": "vanilla", "tdm": "TDM", "tdm2": "2-step TDM"}
TITLES = {"binary": "The paper's setting: binary labels of the visited states (headline)",
          "binary-oracle": "Extension: binary labels with simulator-labelled noisy copies",
          "soft": "Extension: soft distance labels"}


def _seeds(seeds) -> str:
    return f"seeds {seeds[0]}-{seeds[-1]}" if len(seeds) > 1 else f"seed {seeds[0]}"


def claim_statement(c: dict) -> str:
    """One replicate's claim (`tracking.claim` as a dict) in a sentence."""
    n = len(c["seeds"])
    what = "contact ticks" if c["count"] == "contacts" else "contact onsets"
    parts = "; ".join(f"{p['name']}: {p['difference']:+.1f} [{p['ci95'][0]:+.1f}, {p['ci95'][1]:+.1f}], Holm p "
                      f"{p['p_holm']:.3g} ({p['verdict']})" for p in c["comparisons"])
    return (f"Episodes 6-10, mean {what} per episode over {n} seed{'s' if n > 1 else ''}: "
            + ", ".join(f"{NAMES[m]} {v:.1f}" for m, v in c["means"].items())
            + f"; 2-step / vanilla {c['tdm2_over_vanilla']:.1%} [{c['tdm2_over_vanilla_ci95'][0]:.1%}, "
            f"{c['tdm2_over_vanilla_ci95'][1]:.1%}]. {parts}. The paper's claim {phrase(c['verdict'])} here.")


def label_set_statement(rec: dict) -> str:
    """A label set's verdict settled across its replicates, each replicate's beside, ticks then onsets."""
    def line(settled: dict) -> str:
        reps = "; ".join(f"{_seeds(r['seeds'])}: {v}" for r, v in zip(rec["replicates"], settled["replicate_verdicts"]))
        n = len(rec["replicates"])
        return (f"{settled['verdict']} ({reps}" + (f"; {'they agree' if settled['agrees'] else 'they differ'})" if n > 1 else ")"))
    return (f"Counted in contact ticks (Fig. 11e's count): {line(rec['settled'])}. "
            f"Counted in contact onsets: {line(rec['settled_onsets'])}.")


def markdown_table(rows: list[dict], title: str = "") -> str:
    lines = ([f"### {title}", ""] if title else []) + [
        "| method | contact ticks, episode 1 | episodes 6-10: mean [95% interval] (std) over seeds | onsets, episodes "
        "6-10 [95% interval] | cos(n, -grad d) before the balls | last episode | all episodes | tracking error (mm) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        align = "—" if r["alignment_cos_ep6_10"] is None else f"{r['alignment_cos_ep6_10']:+.2f}"
        lines.append(f"| {r['method']} | {r['contacts_first']:.1f} | {r['contacts_ep6_10']:.1f} [{r['contacts_ep6_10_ci95_low']:.1f}, "
                     f"{r['contacts_ep6_10_ci95_high']:.1f}] ({r['contacts_ep6_10_std']:.1f}) | {r['onsets_ep6_10']:.1f} "
                     f"[{r['onsets_ep6_10_ci95_low']:.1f}, {r['onsets_ep6_10_ci95_high']:.1f}] | {align} | "
                     f"{r['contacts_last']:.1f} | {r['contacts_mean']:.1f} | {r['tracking_error_mm']:.0f} |")
    return "\n".join(lines) + "\n"


def markdown(doc: dict) -> str:
    """tracking.md: per label set what it uses, its settled verdict, and per replicate its table and claims."""
    out = [f"Contacts: {COUNTS['contacts']}; beside them {COUNTS['onsets']}. {doc['correction']}.\n"]
    for name, rec in doc["labels"].items():
        out.append(f"## {TITLES.get(name, name)}\n\n{rec['uses']}. {label_set_statement(rec)}\n")
        for k, r in enumerate(rec["replicates"]):
            out.append(markdown_table(r["summary"], f"Replicate {k + 1} ({_seeds(r['seeds'])})"))
            for key in ("claim", "claim_onsets"):
                if r[key]:
                    out.append(claim_statement(r[key]) + "\n")
    return "\n".join(out)


def plot(doc: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"vanilla": "tab:red", "tdm": "tab:blue", "tdm2": "tab:green"}
    labels = {"vanilla": "no modulation", "tdm": "TDM modulation", "tdm2": "2-step TDM modulation"}
    sets = doc["labels"]
    fig, axes = plt.subplots(1, len(sets), figsize=(6 * len(sets), 4), squeeze=False, sharey=True)
    for ax, (name, res) in zip(axes[0], sets.items()):
        for method, by_seed in res["runs"].items():
            c = np.array([[r["contacts"] for r in rows] for rows in by_seed.values()], float)
            ep = np.arange(1, c.shape[1] + 1)
            ax.plot(ep, c.mean(0), "o-", color=colors.get(method), label=labels.get(method, method))
            ax.fill_between(ep, c.min(0), c.max(0), color=colors.get(method), alpha=0.2)
        ax.set_xlabel("episode")
        ax.set_ylabel("contact ticks per episode")
        n = len(next(iter(res["runs"].values())))
        ax.set_title(f"{TITLES.get(name, name)} ({n} seeds, min-max band)", fontsize=8)
        ax.legend()
    fig.tight_layout()
    paths = [out_dir / "contacts.png"]
    write_png(fig, paths[0])
    seed = next(iter(doc["last"].get("vanilla", doc["last"].get(next(iter(doc["last"]))))))
    methods = list(doc["last"])
    fig = plt.figure(figsize=(5 * len(methods), 4.5))
    for i, method in enumerate(methods):
        ep = doc["last"][method][seed]
        ax = fig.add_subplot(1, len(methods), i + 1, projection="3d")
        ax.plot(*np.array(ep["ee_desired"]).T, "k--", lw=1, label="desired")
        ax.plot(*np.array(ep["ee"]).T, color="tab:blue", lw=1.5, label="end effector")
        if len(ep["contact_points"]):
            ax.scatter(*np.array(ep["contact_points"]).T, color="tab:green", s=8, label="contact points")
        for c in doc["balls"][seed]:
            ax.scatter(*c, color="tab:orange", s=120, alpha=0.6)
        ax.set_title(f"{labels.get(method, method)}: {ep['contacts']} contact ticks")
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out_dir / "trajectories.png")
    write_png(fig, paths[1])
    return paths
