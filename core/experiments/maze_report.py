"""The maze experiment's report: its verdicts in English, `maze_contacts.md`'s tables and the curves
(`maze_curves.png`, one row per replicate). Numbers come from `maze.run_protocol`'s document; nothing here
decides a verdict."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from skinsafe.core.experiments.maze import METHODS
from skinsafe.core.experiments.maze_claims import LAST, LEARNED_AT
from skinsafe.core.experiments.verdicts import FAILS, HOLDS, OPEN, phrase

FASTER = {HOLDS: "faster", FAILS: "slower", OPEN: "not resolved"}


def config_text(config: dict) -> str:
    """A configuration in a line: `lr 0.00206, shrink False` (floats to 3 significant digits)."""
    return ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in config.items()) or "defaults"


def _cmp(c: dict) -> str:
    return f"{c['name']}: {c['difference']:+.1f} [{c['ci95'][0]:+.1f}, {c['ci95'][1]:+.1f}], Holm p {c['p_holm']:.3g} ({c['verdict']})"


def claim_statement(c: dict) -> str:
    """One replicate's Fig. 9b claim (`maze_claims.MazeClaim` as a dict) in sentences."""
    what = c["measure"].replace("_", " ")
    order = sorted(c["means"], key=c["means"].get)
    s = (f"{what.capitalize()}, mean [95% interval] over {c['seeds']} seed{'s' if c['seeds'] > 1 else ''}: "
         + ", ".join(f"{m} {c['means'][m]:.1f} [{c['ci95'][m][0]:.1f}, {c['ci95'][m][1]:.1f}]" for m in order) + ". ")
    off = [x for x in c["comparisons"] if x["verdict"] != HOLDS]
    s += (f"The paper's claim {phrase(c['verdict'])} (every -TDM variant below every other "
          "method, Holm-corrected Welch tests)" + (": " + "; ".join(_cmp(x) for x in off) if off else "") + ". "
          f"On the means alone it {'holds' if c['holds_on_means'] else 'does not hold'}.")
    if c["verdict_among_reaching"] is not None:
        s += (f" Among the methods that reach the goal in >= {LEARNED_AT:.0%} of the last {LAST} episodes "
              f"({', '.join(c['reaching'])}) it {phrase(c['verdict_among_reaching'])}.")
    if c["seeds_beaten"]:
        b = c["seeds_beaten"]
        s += (f" Per seed the ordering breaks {len(b)} time{'s' if len(b) > 1 else ''}: a goal-reaching run of another "
              "method touched less than some -TDM run (" + "; ".join(f"{x['method']} seed {x['seed']}: {x[c['measure']]:.0f}"
                                                                        for x in b[:6]) + ("; ..." if len(b) > 6 else "") + ").")
    slow = [m for m, ok in c["learned"].items() if not ok]
    if c["learned"]:
        s += (f" Learning: {', '.join(c['learned'])} reach the goal." if not slow else
              f" Learning: {', '.join(slow)} reach{'es' if len(slow) == 1 else ''} the goal in fewer than {LEARNED_AT:.0%} "
              f"of the last {LAST} episodes.")
    return s


def convergence_statement(c: dict) -> str:
    """Fig. 9c on one replicate in a sentence."""
    rows = ", ".join(f"{m} {v['converged']}/{v['converged'] + v['never']}"
                     + (f" (median episode {v['median_episode_converged']:.0f})" if v["median_episode_converged"] else "")
                     for m, v in c["methods"].items())
    pairs = " ".join(f"{x['name']}: {FASTER[x['verdict']]} (log-rank z {x['difference']:+.2f}, Holm p {x['p_holm']:.3g})."
                     for x in c["comparisons"])
    return (f"Convergence (the first episode from which >= {LEARNED_AT:.0%} of {c['window']} episodes reach the goal; a run "
            f"that never does is censored at episode {c['episodes']}): runs converged {rows}. {pairs}").strip()


def settled_statement(doc: dict) -> str:
    """The verdicts settled across the replicates (a verdict only where every replicate gives it)."""
    def one(name: str, s: dict | None) -> str:
        if s is None:
            return ""
        reps = ", ".join(s["replicate_verdicts"])
        return f"{name}: {s['verdict']} (replicates: {reps})"
    cl = doc["claims"]
    parts = [one("Fig. 9b, total contacts", cl["total"]), one("online contacts only", cl["online"])]
    parts += [one(f"Fig. 9c {k}", {**s, "verdict": FASTER.get(s["verdict"], s["verdict"]),
                                   "replicate_verdicts": [FASTER[v] for v in s["replicate_verdicts"]]})
              for k, s in cl["convergence"].items()]
    return "; ".join(p for p in parts if p) + "."


def markdown(doc: dict) -> str:
    """maze_contacts.md: the settled verdicts, then per replicate its tuning, its table and its claims."""
    out = [settled_statement(doc), "", f"Selection rule: {doc['selection_rule']}. {doc['correction']}.", ""]
    for k, rep in enumerate(doc["replicates"]):
        sm = rep["summary"]
        seeds = sorted({p["seed"] for p in rep["per_seed"]})
        out += [f"## Replicate {k + 1}" + (f" (tuning seeds {', '.join(map(str, rep['tuning_seeds']))})" if rep["tuning_seeds"] else ""), "",
                "| method | total contacts: mean [95% interval] | of them offline | goal rate, last 20 (seeds >= 0.8) | "
                "per seed (total) | configuration |", "| --- | --- | --- | --- | --- | --- |"]
        for m, v in sm["methods"].items():
            lo, hi = v["total_contacts_ci95"]
            per = " / ".join(f"{p['total_contacts']:.0f}" for p in sorted((p for p in rep["per_seed"] if p["method"] == m),
                                                                          key=lambda p: p["seed"]))
            t = rep["tuning"].get(m)
            conf = ("defaults (no tuning)" if t is None else f"trial {t['chosen_index']} of {t['trials']}" if t["met_criterion"]
                    else f"no trial of {t['trials']} met the criterion: trial 0 (defaults)")
            out.append(f"| {m} | {v['total_contacts_mean']:.1f} [{lo:.1f}, {hi:.1f}] | {v['offline_contacts_mean']:.0f} | "
                       f"{v['goal_rate_last_mean']:.2f} ({v['seeds_reaching']}/{v['seeds']}) | {per} | {conf}: "
                       f"{config_text({kk: vv for kk, vv in rep['chosen'][m].items() if kk != 'cost_limit'})} |")
        out += ["", f"Evaluation seeds {', '.join(map(str, seeds))}."]
        for key in ("claim", "claim_online"):
            if sm[key]:
                out += ["", claim_statement(sm[key])]
        out += ["", convergence_statement(sm["convergence"]), ""]
        if rep["tuning"]:
            out += ["| method | trial | configuration | total contacts | goal rate, last 20 | chosen |",
                    "| --- | --- | --- | --- | --- | --- |"]
            for m, t in rep["tuning"].items():
                out += [f"| {m} | {c['trial']} | {config_text(c['config'])} | {c['total_contacts_mean']:.1f} | "
                        f"{c['goal_rate_last_mean']:.2f} | {'**yes**' if i == t['chosen_index'] else ''} |"
                        for i, c in enumerate(t["configs"])]
            out.append("")
    if doc["ablation"]:
        a = doc["ablation"]
        out += [f"## Ablation (replicate 1's configurations, seeds {', '.join(str(p['seed']) for p in a[0]['per_seed'])}, "
                f"the first {a[0]['episodes']} episodes)", "", "| variant | total contacts | difference to the chosen "
                "configuration [Welch 95%] | goal rate, last 20 |", "| --- | --- | --- | --- |"]
        for r in a:
            d = (f"{r['difference_to_chosen']:+.1f} [{r['difference_ci95'][0]:+.1f}, {r['difference_ci95'][1]:+.1f}]"
                 if "difference_to_chosen" in r else "")
            out.append(f"| {r['variant']} | {r['total_contacts_mean']:.1f} [{r['ci95'][0]:.1f}, {r['ci95'][1]:.1f}] | {d} | "
                       f"{r['goal_rate_last_mean']:.2f} |")
    return "\n".join(out) + "\n"


def plot_curves(doc: dict, path: Path, window: int = 5) -> None:
    """Return and cost curves per replicate (one row each), mean over seeds with 95% bands."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reps = doc["replicates"]
    fig, axes = plt.subplots(len(reps), 2, figsize=(11, 3.6 * len(reps)), sharex=True, squeeze=False)
    for k, rep in enumerate(reps):
        for col, key in enumerate(("returns", "costs")):
            ax = axes[k, col]
            for m in rep["summary"]["methods"]:
                curves = np.array([r[key] for r in rep["runs"] if r["method"] == m], float)
                w = max(1, min(window, curves.shape[1] // 3))
                smooth = np.array([np.convolve(c, np.ones(w) / w, mode="valid") for c in curves])
                mean = smooth.mean(0)
                half = 1.96 * smooth.std(0, ddof=1) / np.sqrt(len(smooth)) if len(smooth) > 1 else 0 * mean
                x = np.arange(len(mean)) + w
                color = f"C{METHODS.index(m)}"
                ax.plot(x, mean, label=m, color=color, lw=2 if m.endswith("-TDM") else 1.2)
                ax.fill_between(x, mean - half, mean + half, color=color, alpha=0.15)
            ax.set_ylabel(("episode return" if key == "returns" else "contact events per episode") + f"\nreplicate {k + 1}")
            if key == "costs":
                ax.set_yscale("symlog", linthresh=1)
            ax.grid(alpha=0.3)
            if k == len(reps) - 1:
                ax.set_xlabel("episode")
        axes[k, 0].legend(fontsize=7, ncol=3)
    fig.suptitle("Maze (paper Fig. 9): mean over the evaluation seeds, 95% band (moving average)")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
