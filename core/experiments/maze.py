"""`skinsafe experiment maze`: the strategy-layer experiment of the paper (Fig. 9) in the MuJoCo maze.

Nine methods (SAC, AC, each plain / -RP / -TDM, and the safe-RL baselines RRL, CPO, SQRL), one Ray task
per run (`core.experiments.runner`: local Ray by default, `--address` for a cluster, every finished run
cached in `--out`/tasks and reused by a restarted run).

The full protocol (the default; issue 31), the same effort for every method:

1. tuning (`tune`): one tuner (Optuna's TPE sampler, seeded) gives every method the same number of
   trials (`--trials`, default `TRIALS` = 8) over its own declared search space (`SPACES`: its previous
   default is trial 0; the -TDM mechanisms are switches in the -TDM spaces, the offline phase a switch
   for RRL, SQRL and the -TDM agents) on the tuning seeds (`--tuning-seeds`, default 0-1) for
   `TUNING_EPISODES` (40) episodes. One selection rule (`choose`): the lowest mean total contacts among
   the trials whose mean goal rate over the last 20 of those episodes is at least 0.8; a method with no
   such trial is reported as never meeting the criterion and evaluated at its default (no rescue);
2. evaluation: each chosen configuration on held-out seeds (`--seeds`, default 10-19), reported per
   seed and as means with 95% intervals; the claim (Fig. 9b: the -TDM variants have the fewest total
   contacts) is decided per pair by Welch's interval of the difference (`claim_check`);
3. ablation: each -TDM extra removed in turn (`TDM_EXTRAS`) and each one that applies given to RRL and
   SQRL (`BASELINE_EXTRAS`), on the first three evaluation seeds (10-12, `--ablation-seeds`) for the first
   `ABLATION_EPISODES` (30) episodes, where nearly all -TDM contacts happen, each against the same
   episodes of its method's evaluation runs (a run's first episodes do not depend on how many follow).

Replicates (`--replicates`, default 2): tuning and evaluation run again with the next tuning seeds (0-1,
then 2-3) and another sampler seed; each replicate's verdicts are recorded (`replicates`) and the claim
is stated only where they agree (`verdict_agrees`; else "not settled"), Fig. 9c's too. Fig. 9c (faster convergence:
`convergence`): per run the first episode from which the goal is reached in >= 80% of `WINDOW`
episodes (never: episodes + 1), each -TDM variant against its plain method by Welch's interval.

The budget (issue 31: the full grids within 60 min on 2 cores) is set by the cost of a run: ~3-5 ms of
CPU per macro-action for the SAC family (one gradient step per step), ~1 ms for AC and CPO; a run that
never reaches the goal takes all 200 macro-actions of every episode. README "Equal effort" has the estimate.

`--demo` and `--quick` are single-stage runs of the default configurations (the demo's reduced run and
the test suite's smoke run). Writes `maze_results.json` (`summary`, `eval_seeds`, `tuning`, `per_seed`,
`ablation`, `runs` with every evaluation run's per-episode returns, costs, goals and TDM fit records),
`maze_contacts.md` (the tables) and `maze_curves.png` (return and cost curves, 95% bands).

Budget: the maze has 72 (cell, heading) states, 68 wall-facing moves and a 12-action shortest path; a
random walk needs a median ~500 macro-actions to reach the goal (20% within 200), so an episode is at
most 200 macro-actions; 80 episodes per evaluation run (on every seed of the earlier 200-episode grid
SAC, AC and both -TDM variants were in their final behaviour by episode 60: goal rate >= 0.8 over the 20
episodes from then on).
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from skinsafe.core.experiments.maze_runs import run_one
from skinsafe.core.experiments.runner import provenance, run_tasks
from skinsafe.core.experiments.stats import compare, diff_ci, mean_ci, parse_seeds
from skinsafe.core.skin.files import atomic_write

METHODS = ("SAC", "SAC-RP", "SAC-TDM", "AC", "AC-RP", "AC-TDM", "RRL", "CPO", "SQRL")
TDM_METHODS = ("SAC-TDM", "AC-TDM")
FULL = dict(seeds=10, episodes=80, max_steps=200)  # the evaluation stage of the full protocol
PROTOCOL = dict(tuning_seeds=[0, 1], eval_seeds=list(range(10, 20)), ablation_seeds=3)  # the first 3 evaluation seeds
TUNING_EPISODES = 40
TRIALS = 8  # tuning trials per method, the same for every method
ROUND = 4  # trials asked of every method's sampler at once (run together on Ray, then told in a fixed order)
REPLICATES = 2
WINDOW = 10  # episodes over which convergence (Fig. 9c) is judged
ABLATION_EPISODES = 30
DEMO = dict(seeds=2, episodes=60, max_steps=200)
QUICK = dict(seeds=1, episodes=2, max_steps=20)
PRESETS = {"full": FULL, "demo": DEMO, "quick": QUICK}
LAST = 20  # episodes over which the final goal rate is measured
LEARNED_AT = 0.8  # a method "reaches the goal" when its mean goal rate over the last LAST episodes is at least this

# Each method's own search space: keyword -> (its default, the trial-0 value; the values tried): a list
# is a switch or a choice, ("log" | "float", low, high) a range. The -TDM mechanisms are switches; the
# offline phase (recovery-rl's 4,000 random transitions) is a switch for every agent that can use it.
LR = (3e-3, ("log", 3e-4, 1e-2))
TDM_SPACE = {"lr": LR, "prior_count": (0.01, ("log", 1e-3, 1.0)), "raw_floor": (0.05, [0.05, 0.0]),
             "unfiltered_entropy": (True, [True, False]), "shrink": (True, [True, False]),
             "contact_steps": (100, [100, 0]), "offline_transitions": (0, [0, 4000])}
SPACES = {
    "SAC": {"lr": LR, "entropy_share": (0.3, ("float", 0.1, 0.5))},
    "SAC-RP": {"lr": LR, "cost_penalty": (1.0, ("log", 1.0, 100.0))},  # 50: recovery-rl's maze reward penalty
    "SAC-TDM": TDM_SPACE,
    "AC": {"lr": LR, "entropy_coef": (0.02, ("log", 0.005, 0.1))},
    "AC-RP": {"lr": LR, "cost_penalty": (1.0, ("log", 1.0, 100.0))},
    "AC-TDM": TDM_SPACE,
    # RRL, SQRL defaults: recovery-rl's maze (eps 0.15, gamma_safe 0.5, SQRL nu from 100, 4,000 offline transitions)
    "RRL": {"lr": LR, "eps_risk": (0.15, ("float", 0.05, 0.5)), "offline_transitions": (4000, [4000, 0])},
    "CPO": {"lr": LR, "target_kl": (0.02, ("log", 0.005, 0.05))},  # the cost budget is the maze's (`cpo_budget`)
    "SQRL": {"lr": LR, "nu": (100.0, ("log", 1.0, 500.0)), "offline_transitions": (4000, [4000, 0])},
}
# The -TDM extras, each removed in turn (ablation): what is removed and the keyword that removes it.
TDM_EXTRAS = (
    ("5% uniform floor", {"raw_floor": 0.0}),
    ("entropy on the unfiltered policy", {"unfiltered_entropy": False}),
    ("visit-count shrinkage", {"shrink": False}),
    ("contact refits (100 steps, the contact in every batch)", {"contact_steps": 0}),
    ("tuned prior count (-> 0.5, its value before it was tuned)", {"prior_count": 0.5}),
)
# The extras that apply to RRL and SQRL, given to each in turn. The entropy term does not apply: their
# actors already learn the unfiltered policy with its entropy; the prior count is tuned for every method.
BASELINE_EXTRAS = (
    ("5% uniform floor", {"floor": 0.05}),
    ("visit-count shrinkage", {"shrink": True}),
    ("contact refits (100 steps, the contact in every batch)", {"contact_steps": 100}),
)
BASELINES_GIVEN = ("RRL", "SQRL")
# Relative CPU cost of one run (measured), so every stage starts the longest first.
RUN_COST = {"SQRL": 5.0, "RRL": 5.0, "SAC-RP": 4.0, "SAC": 2.5, "CPO": 1.0, "SAC-TDM": 1.5, "AC-TDM": 1.5,
            "AC-RP": 0.4, "AC": 0.4}


def cpo_budget(episodes: int) -> float:
    """CPO's cost limit per episode: the maze's 68 wall-facing moves (`maze_env.wall_moves`), each of which
    a learner that cannot see the walls must try once, spread over the run (0.85 at 80 episodes). A
    trained policy needs no contact at all; a larger budget licenses contacts no learner needs."""
    from skinsafe.core.learn.maze_env import LAYOUT, parse_layout, wall_moves

    return wall_moves(parse_layout(LAYOUT)[0]) / episodes


def add_arguments(p) -> None:
    p.add_argument("--out", default="results/maze", help="folder for the plots, table and JSON (default: %(default)s)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--full", action="store_const", dest="preset", const="full",
                   help=f"the full protocol (default): tuning, evaluation on held-out seeds, ablation; {FULL}")
    g.add_argument("--demo", action="store_const", dest="preset", const="demo", help=f"the demo's reduced run: {DEMO}")
    g.add_argument("--quick", action="store_const", dest="preset", const="quick", help=f"smoke test: {QUICK}")
    p.set_defaults(preset="full")
    p.add_argument("--seeds", help="evaluation seeds, a range or a list: 10-19 (full default) or 11,12,13 "
                                   "(--demo/--quick: 0-1 / 0)")
    p.add_argument("--tuning-seeds", help="tuning seeds of the full protocol (default 0-1)")
    p.add_argument("--tuning-episodes", type=int, default=TUNING_EPISODES,
                   help="episodes of every tuning run (default %(default)s, at most --episodes)")
    p.add_argument("--trials", type=int, default=TRIALS, help="tuning trials per method, the same for every method "
                                                               "(default %(default)s)")
    p.add_argument("--replicates", type=int, default=REPLICATES,
                   help="tuning + evaluation replicates, each on the next tuning seeds (default %(default)s)")
    p.add_argument("--ablation-seeds", help="evaluation seeds the ablation runs on (default the first three: 10-12)")
    p.add_argument("--ablation-episodes", type=int, default=ABLATION_EPISODES,
                   help="episodes of every ablation run (default %(default)s, at most --episodes)")
    p.add_argument("--no-ablation", action="store_true", help="full protocol without the ablation stage")
    p.add_argument("--episodes", type=int, help="training episodes per run (overrides the preset)")
    p.add_argument("--max-steps", type=int, help="macro-actions per episode (overrides the preset)")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of %(default)s")
    p.add_argument("--tdm-refit-steps", type=int, help="-TDM agents: gradient steps per periodic refit (default 25)")
    p.add_argument("--tdm-unseen-max", type=float, help="-TDM agents: most danger the filter gives an untried move (default 0.8)")
    p.add_argument("--tdm-prior-count", type=float,
                   help="-TDM agents: tries of a move after which the filter trusts the TDM's danger half-way (default 0.01)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s; 0: the tasks in this process, no Ray)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every task instead of reusing finished ones")
    p.add_argument("--no-progress", action="store_true")


def _mean_std(x) -> tuple[float, float]:
    x = np.asarray(x, float)
    return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0


def run_row(r: dict) -> dict:
    """One run in a line: `total_contacts` (every contact the robot made: online, plus the offline phase's
    of RRL and SQRL), `online_contacts`, `offline_contacts`, goal rates (all episodes, last LAST)."""
    online, offline = float(sum(r["costs"])), float(r.get("offline_contacts", 0))
    return {"method": r["method"], "seed": r["seed"], "total_contacts": online + offline, "online_contacts": online,
            "offline_contacts": offline, "goal_rate": float(np.mean(r["goals"])),
            "goal_rate_last": float(np.mean(r["goals"][-LAST:])), "cpu_seconds": r.get("cpu_seconds")}


def summarise(runs: list[dict], methods: list[str], tuning: dict | None = None) -> dict:
    """Per-method totals and goal rates (mean, std and 95% interval over seeds), whether tuning met the goal
    criterion (`met_criterion`, with `tuning`), the claim check and Fig. 9c's `convergence`."""
    rows = {}
    per_seed = [run_row(r) for r in runs]
    for m in methods:
        rs = [r for r in runs if r["method"] == m]
        per = [p for p in per_seed if p["method"] == m]
        row = {}
        for key in ("total_contacts", "online_contacts", "offline_contacts", "goal_rate", "goal_rate_last"):
            x = [p[key] for p in per]
            row[f"{key}_mean"], row[f"{key}_std"] = _mean_std(x)
            row[f"{key}_ci95"] = mean_ci(x)[1]
        rows[m] = {**row, "seeds_reaching": int(sum(p["goal_rate_last"] >= LEARNED_AT for p in per)),
                   "mean_return": float(np.mean([np.mean(r["returns"]) for r in rs])),
                   "mean_steps": float(np.mean([np.mean(r["steps"]) for r in rs])),
                   "seconds_mean": float(np.mean([r.get("seconds", np.nan) for r in rs])), "seeds": len(rs)}
    claim = claim_check(rows, per_seed)
    if any(p["offline_contacts"] for p in per_seed):
        claim["online_only"] = claim_check(rows, per_seed, key="online_contacts")
        claim["statement"] += (" Counting only the online contacts (recovery-rl's accounting, the offline phase's "
                               "apart): " + claim["online_only"]["statement"])
    if tuning:
        for m in methods:
            rows[m]["met_criterion"] = tuning[m]["met_criterion"]
        never = [m for m in methods if not tuning[m]["met_criterion"]]
        if never:
            claim["never_met_criterion"] = never
            claim["statement"] += (f" Tuning: {', '.join(never)} never met the goal criterion in {tuning[never[0]]['trials']} "
                                   "trials (evaluated at the default configuration).")
    return {"methods": rows, "claim": claim, "convergence": convergence(runs, methods)}


def converged_at(goals, window: int = WINDOW, learned_at: float = LEARNED_AT) -> int:
    """The first episode (1-based) from which the goal is reached in >= `learned_at` of `window` episodes;
    never: the number of episodes + 1."""
    g = np.asarray(goals, float)
    hit = [e for e in range(len(g) - window + 1) if g[e:e + window].mean() >= learned_at]
    return hit[0] + 1 if hit else len(g) + 1


def convergence(runs: list[dict], methods: list[str]) -> dict:
    """Fig. 9c, faster convergence: per method the mean convergence episode (`converged_at`) with its 95%
    interval and how many runs never converged; per -TDM variant against its plain method, Welch's interval
    of (plain - TDM) episodes: "faster" when it lies above 0, "slower" below, else "not resolved"."""
    eps = {m: [converged_at(r["goals"]) for r in runs if r["method"] == m] for m in methods}
    rows = {m: {"episode_mean": mean_ci(x)[0], "ci95": mean_ci(x)[1], "never": int(sum(
        e > len(r["goals"]) for e, r in zip(x, [r for r in runs if r["method"] == m])))} for m, x in eps.items() if x}
    pairs = {}
    for t in TDM_METHODS:
        if t in rows and t[:-4] in rows:
            d, ci = diff_ci(eps[t], eps[t[:-4]])
            pairs[f"{t} vs {t[:-4]}"] = {"difference": d, "ci95": ci,
                                         "verdict": {"lower": "faster", "higher": "slower"}.get(compare(ci), "not resolved")}
    s = (f"Convergence (first episode from which >= {LEARNED_AT:.0%} of {WINDOW} episodes reach the goal; never: episodes"
         " + 1): " + ", ".join(f"{m} {v['episode_mean']:.1f} [{v['ci95'][0]:.1f}, {v['ci95'][1]:.1f}]" for m, v in rows.items())
         + ". " + " ".join(f"{k}: {p['verdict']} by {p['difference']:.1f} episodes [{p['ci95'][0]:.1f}, {p['ci95'][1]:.1f}]."
                           for k, p in pairs.items()))
    return {"window": WINDOW, "methods": rows, "pairs": pairs, "statement": s.strip()}


def settle(claim: dict, reps: list[dict]) -> dict:
    """The first replicate's claim with every replicate's verdict beside it: `verdict_agrees` when all
    replicates give the same verdicts (total and online-only contacts); where they differ the verdict is
    "not settled" (never the first replicate's alone)."""
    v = [r["summary"]["claim"]["verdict"] for r in reps]
    vo = [r["summary"]["claim"].get("online_only", {}).get("verdict") for r in reps]
    agrees = len(set(v)) == 1 and len(set(vo)) == 1
    out = dict(claim, verdict_agrees=agrees, replicate_verdicts=v)
    if len(reps) > 1:
        out["statement"] = claim["statement"] + " Replicates: " + "; ".join(
            f"tuning seeds {r['tuning_seeds'][0]}-{r['tuning_seeds'][-1]}: {a}" + (f" (online only: {b})" if b else "")
            for r, a, b in zip(reps, v, vo)) + (". The verdicts agree." if agrees else ". The verdicts differ: not settled.")
    if len(set(v)) > 1:
        out.update(verdict="not settled", holds=False)
    if len(set(vo)) > 1:
        out["online_only"] = dict(claim["online_only"], verdict="not settled", holds=False)
    return out


def settle_convergence(conv: dict, reps: list[dict]) -> dict:
    """Fig. 9c as `settle` does the claim: each pair's verdict per replicate (`replicate_verdicts`); a pair
    whose replicates differ is "not settled"."""
    pairs = {}
    for k, p in conv["pairs"].items():
        v = [r["summary"]["convergence"]["pairs"].get(k, {}).get("verdict") for r in reps]
        pairs[k] = dict(p, replicate_verdicts=v, verdict=p["verdict"] if len(set(v)) == 1 else "not settled")
    s = conv["statement"]
    if len(reps) > 1:
        s += " Replicates: " + "; ".join(f"{k}: {', '.join(map(str, p['replicate_verdicts']))}" + (
            "" if p["verdict"] != "not settled" else " (not settled)") for k, p in pairs.items()) + "."
    return dict(conv, pairs=pairs, statement=s)


def replicate_record(rep: dict, runs: list[dict]) -> dict:
    """One replicate in brief: its tuning seeds, chosen configurations, totals and verdicts."""
    sm = rep["summary"]
    return {"tuning_seeds": rep["tuning_seeds"], "chosen": {m: t["chosen"] for m, t in rep["tuning"].items()},
            "met_criterion": {m: t["met_criterion"] for m, t in rep["tuning"].items()},
            "total_contacts_mean": {m: v["total_contacts_mean"] for m, v in sm["methods"].items()},
            "per_seed": [run_row(r) for r in runs], "verdict": sm["claim"]["verdict"],
            "online_only_verdict": sm["claim"].get("online_only", {}).get("verdict"),
            "convergence": {k: p["verdict"] for k, p in sm["convergence"]["pairs"].items()},
            "statement": sm["claim"]["statement"]}


def _pairs(tdm: list[str], other: list[str], totals: dict) -> dict:
    """Welch's interval of (other - TDM) contacts for every pair, and its verdict (`stats.compare`)."""
    out = {}
    for t in tdm:
        for o in other:
            d, ci = diff_ci(totals[t], totals[o])
            out[f"{t} vs {o}"] = {"difference": d, "ci95": ci, "verdict": compare(ci)}
    return out


def claim_check(rows: dict, per_seed: list[dict] | None = None, learned_at: float = LEARNED_AT,
                key: str = "total_contacts") -> dict:
    """The paper's claim (Fig. 9b): the -TDM variants have the fewest total contact events (`key` per run,
    from `per_seed`; without it the means in `rows`). `holds`: for every -TDM variant and every other
    method, the 95% (Welch) interval of the difference of means lies above 0 (with one seed per method:
    the means alone). `holds_on_means`: the plain ordering of the means. The same among the methods that
    reach the goal (mean goal rate over the last LAST episodes >= `learned_at`); `seeds_beaten`: runs of
    another method that reached the goal with fewer contacts than some -TDM run. `learned`: whether SAC,
    AC and their -TDM variants reach the goal."""
    per_seed = per_seed or []
    totals = {m: [p[key] for p in per_seed if p["method"] == m] or [v[f"{key}_mean"]] for m, v in rows.items()}
    tdm = [m for m in rows if m.endswith("-TDM")]
    other = [m for m in rows if not m.endswith("-TDM")]
    if not tdm or not other:
        return {"holds": None, "statement": "needs at least one -TDM method and one other method"}
    mean = {m: float(np.mean(v)) for m, v in totals.items()}
    ci = {m: mean_ci(v)[1] for m, v in totals.items()}
    best_tdm, best_other, worst_tdm = min(tdm, key=mean.get), min(other, key=mean.get), max(tdm, key=mean.get)
    pairs = _pairs(tdm, other, totals)
    holds = all(p["verdict"] == "lower" for p in pairs.values())
    holds_on_means = mean[worst_tdm] < mean[best_other]
    ratio = mean[best_other] / mean[best_tdm] if mean[best_tdm] > 0 else float("inf")
    n_seeds = min(len(v) for v in totals.values())
    reach = {m for m, v in rows.items() if v.get("goal_rate_last_mean") is not None and v["goal_rate_last_mean"] >= learned_at}
    learners = [m for m in ("SAC", "AC", "SAC-TDM", "AC-TDM") if m in rows and "goal_rate_last_mean" in rows[m]]
    learned = {m: rows[m]["goal_rate_last_mean"] >= learned_at for m in learners}
    what = key.replace("_", " ")
    s = (f"{what.capitalize()}, mean [95% interval] over {n_seeds} seed{'s' if n_seeds > 1 else ''}: "
         + ", ".join(f"{m} {mean[m]:.1f} [{ci[m][0]:.1f}, {ci[m][1]:.1f}]" for m in sorted(rows, key=mean.get)) + ". ")
    if holds:
        s += (f"The paper's claim holds: every -TDM variant has fewer {what} than every other method, each "
              f"difference's 95% interval above 0; the best, {best_tdm}, is {ratio:.2f}x lower than the best other "
              f"method, {best_other}.")
    else:
        bad = {k: p for k, p in pairs.items() if p["verdict"] != "lower"}
        reversed_ = any(p["verdict"] == "higher" for p in bad.values())
        s += (("The paper's claim does not hold here: " if reversed_ else
               "The paper's claim is not resolved at 95% here (no pair reversed, some intervals contain 0): ") + "; ".join(
            f"{k}: difference {p['difference']:.1f} [{p['ci95'][0]:.1f}, {p['ci95'][1]:.1f}] ({p['verdict']})"
            for k, p in bad.items()) + f". On the means alone it {'holds' if holds_on_means else 'does not hold'}.")
    own = [f"{m} has {100 * (1 - mean[m] / mean[m[:-4]]):.0f}% fewer contacts than {m[:-4]}"
           for m in tdm if m[:-4] in mean and mean[m[:-4]] > 0]
    if own:
        s += " " + "; ".join(own) + "."
    tdm_r, other_r = [m for m in tdm if m in reach], [m for m in other if m in reach]
    holds_r = None
    if tdm_r and other_r:
        pr = {k: p for k, p in pairs.items() if k.split(" vs ")[0] in tdm_r and k.split(" vs ")[1] in other_r}
        holds_r = all(p["verdict"] == "lower" for p in pr.values())
        who = ", ".join(f"{m} on {rows[m].get('seeds_reaching', n_seeds)}/{rows[m].get('seeds', n_seeds)} seeds" for m in sorted(reach))
        s += (f" Among the methods that reach the goal in >= {learned_at:.0%} of the last {LAST} episodes ({who}) "
              f"the claim {'holds' if holds_r else 'does not hold'}"
              + ("" if holds_r else ": " + ", ".join(k for k, p in pr.items() if p["verdict"] != "lower")) + ".")
    beaten = []
    for p in per_seed:
        if p["method"] in other and p["goal_rate_last"] >= learned_at:
            worse = [q for q in per_seed if q["method"] in tdm and q[key] > p[key]]
            if worse:
                beaten.append({"method": p["method"], "seed": p["seed"], key: p[key],
                               "above": sorted(f"{q['method']} seed {q['seed']}" for q in worse)})
    if beaten:
        s += (f" Per seed the ordering breaks {len(beaten)} time{'s' if len(beaten) > 1 else ''}: a goal-reaching run of "
              "another method touched less than some -TDM run (" + "; ".join(
                  f"{b['method']} seed {b['seed']}: {b[key]:.0f}" for b in beaten[:6]) + ("; ..." if len(beaten) > 6 else "") + ").")
    if learned:
        slow = [m for m, ok in learned.items() if not ok]
        s += (f" Learning: {', '.join(learned)} reach the goal in >= {learned_at:.0%} of the last {LAST} episodes."
              if not slow else f" Learning: {', '.join(slow)} reach{'es' if len(slow) == 1 else ''} the goal in fewer than "
              f"{learned_at:.0%} of the last {LAST} episodes, so this budget does not show the trained behaviour of the paper.")
    verdict = "holds" if holds else "does not hold" if any(p["verdict"] == "higher" for p in pairs.values()) else "not resolved"
    return {"holds": bool(holds), "verdict": verdict, "holds_on_means": bool(holds_on_means), "holds_among_goal_reaching": holds_r,
            "measure": key, "pairs": pairs, "best_tdm": best_tdm, "best_other": best_other,
            "ratio_best_other_to_best_tdm": ratio, "seeds_beaten": beaten, "learned": learned,
            "all_learned": bool(learned) and all(learned.values()), "statement": s}


# -- the tuning protocol ----------------------------------------------------------------------------
def choose(rows: list[dict], learned_at: float = LEARNED_AT) -> int | None:
    """Index of the chosen trial: the lowest mean total contacts among those whose mean goal rate over the
    last LAST episodes is >= `learned_at` (ties: the earlier trial); None when no trial meets it."""
    ok = [i for i, r in enumerate(rows) if r["goal_rate_last_mean"] >= learned_at]
    return min(ok, key=lambda i: (rows[i]["total_contacts_mean"], i)) if ok else None


def objective(row: dict, learned_at: float = LEARNED_AT) -> float:
    """The number the sampler minimises, ordered as `choose` orders: a trial meeting the goal criterion
    scores its contacts, one missing it 10^6 per goal rate short of the criterion plus its contacts."""
    short = max(0.0, learned_at - row["goal_rate_last_mean"])
    return row["total_contacts_mean"] + (1e6 * (1 + short) if short > 0 else 0.0)


CRITERION = (f"lowest mean total contacts among the trials whose mean goal rate over the last {LAST} "
             f"episodes on the tuning seeds is >= {LEARNED_AT}; none: the method never met the criterion "
             "(evaluated at its default configuration)")


def agent_kw(method: str, config: dict, episodes: int, extra: dict | None = None) -> dict:
    """The agent's keyword arguments for a configuration: CPO gets the maze's cost budget, -TDM agents
    the command line's TDM overrides (`extra`)."""
    kw = dict(config)
    if method == "CPO":
        kw.setdefault("cost_limit", cpo_budget(episodes))
    if extra and method in TDM_METHODS:
        kw.update(extra)
    return kw


def _task(method, seed, cfg, kw) -> dict:
    t = {"method": method, "seed": int(seed), "episodes": cfg["episodes"], "max_steps": cfg["max_steps"]}
    if kw:
        t["agent_kw"] = kw
    return t


def _run(tasks, out, args, desc, keep_ray: bool = False) -> list[dict]:
    return run_tasks(run_one, tasks, out / "tasks", address=args.address, workers=args.workers,
                     progress=not args.no_progress, desc=desc, fresh=args.fresh,
                     cost=lambda t: RUN_COST[t["method"]] * t["episodes"] * t["max_steps"], keep_ray=keep_ray)


def _stop_ray() -> None:
    """End a Ray this process started (without importing Ray when no stage needed it)."""
    if "ray" in sys.modules and sys.modules["ray"].is_initialized():
        sys.modules["ray"].shutdown()


def config_text(config: dict) -> str:
    """A configuration in a line: `lr 0.00206, shrink False` (floats to 3 significant digits)."""
    return ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in config.items()) or "defaults"


def _distribution(values):
    import optuna.distributions as od

    if isinstance(values, list):
        return od.CategoricalDistribution(values)
    kind, lo, hi = values
    return od.FloatDistribution(lo, hi, log=kind == "log")


def tune(methods, cfg, seeds, trials, out, args, extra, sampler_seed: int = 0) -> tuple[dict, list[dict]]:
    """Stage 1: `trials` Optuna trials per method over its `SPACES` entry (trial 0 its defaults; TPE, seeded,
    asked `ROUND` at a time per method, all of a round run together on Ray and told in a fixed order, so the
    trials are a function of the runs), each on the tuning seeds; the record (per method: every trial, the
    chosen one by `choose`, or none) and the runs."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    studies, dists, rows, runs = {}, {}, {m: [] for m in methods}, []
    for m in methods:
        sampler = optuna.samplers.TPESampler(seed=sampler_seed, n_startup_trials=max(1, trials // 2), constant_liar=True)
        studies[m] = optuna.create_study(direction="minimize", sampler=sampler)
        studies[m].enqueue_trial({k: default for k, (default, _) in SPACES[m].items()})
        dists[m] = {k: _distribution(values) for k, (_, values) in SPACES[m].items()}
    while len(rows[methods[0]]) < trials:
        n = min(ROUND, trials - len(rows[methods[0]]))
        asked = {m: [studies[m].ask(dists[m]) for _ in range(n)] for m in methods}
        tasks = [_task(m, s, cfg, agent_kw(m, t.params, cfg["episodes"], extra)) for m in methods for t in asked[m] for s in seeds]
        done = _run(tasks, out, args, f"maze tuning (seeds {seeds[0]}-{seeds[-1]}), {len(rows[methods[0]]) + n}/{trials} trials",
                    keep_ray=True)  # the next round and the evaluation stage reuse this Ray
        runs += done
        it = iter(done)
        for m in methods:
            for t in asked[m]:
                rs = [run_row(next(it)) for _ in seeds]
                row = {"trial": t.number, "config": t.params, "agent_kw": agent_kw(m, t.params, cfg["episodes"], extra),
                       "total_contacts_mean": float(np.mean([r["total_contacts"] for r in rs])),
                       "goal_rate_last_mean": float(np.mean([r["goal_rate_last"] for r in rs])),
                       "per_seed": [{k_: r[k_] for k_ in ("seed", "total_contacts", "goal_rate_last")} for r in rs]}
                studies[m].tell(t, objective(row))
                rows[m].append(row)
    record = {}
    for m in methods:
        i = choose(rows[m])
        record[m] = {"space": {k: values for k, (_, values) in SPACES[m].items()}, "trials": len(rows[m]),
                     "configs": rows[m], "tuning_seeds": list(seeds), "episodes": cfg["episodes"],
                     "sampler": f"optuna {optuna.__version__} TPE, seed {sampler_seed}", "met_criterion": i is not None,
                     "chosen": rows[m][0 if i is None else i]["config"], "chosen_index": i, "criterion": CRITERION}
    return record, runs


def ablation_tasks(chosen: dict, methods, cfg, seeds) -> list[tuple[dict, dict]]:
    """(row head, task) for every ablation run: each -TDM extra removed from a -TDM method's chosen
    configuration, each applicable extra given to RRL and SQRL (variants identical to the chosen
    configuration are left out: they are its evaluation runs)."""
    out = []
    for m in methods:
        extras = TDM_EXTRAS if m in TDM_METHODS else BASELINE_EXTRAS if m in BASELINES_GIVEN else ()
        for what, delta in extras:
            kw = {**chosen[m], **delta}
            if kw == chosen[m]:
                continue
            head = {"method": m, "variant": f"{m} {'-' if m in TDM_METHODS else '+'} {what.split(' (')[0]}",
                    "removed": what if m in TDM_METHODS else None, "added": None if m in TDM_METHODS else what,
                    "agent_kw": kw}
            out += [(head, _task(m, s, cfg, kw)) for s in seeds]
    return out


def first_episodes(run: dict, n: int) -> dict:
    """A run cut to its first `n` episodes (training is causal: those episodes are the same in a shorter run)."""
    return {**run, **{k: run[k][:n] for k in ("returns", "costs", "goals", "steps")}}


def ablation_rows(heads_runs, eval_runs: list[dict], chosen: dict) -> list[dict]:
    """The ablation table: per method its chosen configuration (its evaluation runs on the ablation's seeds,
    cut to the ablation's episodes), then each variant: mean total contacts and its 95% interval, the
    difference to the chosen one with Welch's interval."""
    groups: dict[str, tuple[dict, list]] = {}
    for head, run in heads_runs:
        groups.setdefault(head["variant"], (head, []))[1].append(run_row(run))
    seeds = {r["seed"] for _, r in heads_runs}
    episodes = min((len(r["costs"]) for _, r in heads_runs), default=0)
    rows, base = [], {}
    for m in dict.fromkeys(h["method"] for h, _ in groups.values()):
        ref = [run_row(first_episodes(r, episodes)) for r in eval_runs if r["method"] == m and r["seed"] in seeds]
        base[m] = [r["total_contacts"] for r in ref]
        mu, ci = mean_ci(base[m])
        rows.append({"method": m, "variant": f"{m} (chosen configuration)", "removed": None, "added": None,
                     "agent_kw": chosen[m], "total_contacts_mean": mu, "ci95": ci, "episodes": episodes,
                     "goal_rate_last_mean": float(np.mean([r["goal_rate_last"] for r in ref])), "seeds": len(ref),
                     "per_seed": [{k: r[k] for k in ("seed", "total_contacts", "goal_rate_last")} for r in ref]})
        for head, rs in (g for g in groups.values() if g[0]["method"] == m):
            x = [r["total_contacts"] for r in rs]
            mu, ci = mean_ci(x)
            d, dci = diff_ci(base[m], x)
            rows.append({**head, "total_contacts_mean": mu, "ci95": ci, "episodes": episodes,
                         "goal_rate_last_mean": float(np.mean([r["goal_rate_last"] for r in rs])),
                         "difference_to_chosen": d, "difference_ci95": dci, "seeds": len(rs),
                         "per_seed": [{k: r[k] for k in ("seed", "total_contacts", "goal_rate_last")} for r in rs]})
    return rows


# -- output -----------------------------------------------------------------------------------------
def markdown_table(summary: dict, per_seed: list[dict] | None = None, tuning: dict | None = None,
                   ablation: list[dict] | None = None) -> str:
    n = max((v["seeds"] for v in summary["methods"].values()), default=0)
    lines = ["| method | total contact events: mean [95% interval] | std | of them offline | goal rate | goal rate, "
             "last 20 episodes (seeds >= 0.8) | seeds |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for m, v in summary["methods"].items():
        lo, hi = v["total_contacts_ci95"]
        lines.append(f"| {m} | {v['total_contacts_mean']:.1f} [{lo:.1f}, {hi:.1f}] | {v['total_contacts_std']:.1f} | "
                     f"{v['offline_contacts_mean']:.0f} | {v['goal_rate_mean']:.2f} | {v['goal_rate_last_mean']:.2f} "
                     f"({v['seeds_reaching']}/{v['seeds']}) | {v['seeds']} |")
    text = "\n".join(lines) + "\n\n" + summary["claim"]["statement"] + "\n\n" + summary["convergence"]["statement"] + "\n"
    if per_seed and n > 1:
        seeds = sorted({p["seed"] for p in per_seed})
        text += ("\nPer seed: total contacts (goal rate over the last 20 episodes)\n\n| method | "
                 + " | ".join(f"seed {s}" for s in seeds) + " |\n| --- |" + " --- |" * len(seeds) + "\n")
        for m in summary["methods"]:
            by = {p["seed"]: p for p in per_seed if p["method"] == m}
            text += f"| {m} | " + " | ".join(
                f"{by[s]['total_contacts']:.0f} ({by[s]['goal_rate_last']:.2f})" if s in by else "-" for s in seeds) + " |\n"
    if tuning:
        text += "\nTuning (" + CRITERION + "):\n\n| method | trial | configuration | total contacts | goal rate, last 20 | chosen |\n| --- | --- | --- | --- | --- | --- |\n"
        for m, rec in tuning.items():
            for i, c in enumerate(rec["configs"]):
                text += (f"| {m} | {c['trial']} | {config_text(c['config'])} | {c['total_contacts_mean']:.1f} | "
                         f"{c['goal_rate_last_mean']:.2f} | {'**yes**' if i == rec['chosen_index'] else ''} |\n")
            if not rec["met_criterion"]:
                text += f"| {m} | — | no trial met the goal criterion: evaluated at trial 0 (default) | | | |\n"
    if ablation:
        text += (f"\nAblation (seeds {', '.join(str(p['seed']) for p in ablation[0]['per_seed'])}, the first "
                 f"{ablation[0]['episodes']} episodes): total contacts, mean [95% interval]; difference to the chosen "
                 "configuration [Welch 95% interval]\n\n| variant | removed / added | total contacts | difference | "
                 "goal rate, last 20 |\n| --- | --- | --- | --- | --- |\n")
        for r in ablation:
            d = (f"{r['difference_to_chosen']:+.1f} [{r['difference_ci95'][0]:+.1f}, {r['difference_ci95'][1]:+.1f}]"
                 if "difference_to_chosen" in r else "")
            text += (f"| {r['variant']} | {r['removed'] or (('+ ' + r['added']) if r['added'] else '')} | "
                     f"{r['total_contacts_mean']:.1f} [{r['ci95'][0]:.1f}, {r['ci95'][1]:.1f}] | {d} | {r['goal_rate_last_mean']:.2f} |\n")
    return text


def plot_curves(runs: list[dict], methods: list[str], path: Path, window: int = 5) -> None:
    """Return and cost curves, mean over seeds with 95% confidence bands: SAC/AC families and safe-RL baselines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [[m for m in methods if m.startswith(("SAC", "AC"))], [m for m in methods if m.endswith("-TDM") or m in ("RRL", "CPO", "SQRL")]]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for col, group in enumerate(groups):
        for row, key in enumerate(("returns", "costs")):
            ax = axes[row, col]
            for m in group:
                curves = np.array([r[key] for r in runs if r["method"] == m], float)
                if curves.size == 0:
                    continue
                k = max(1, min(window, curves.shape[1] // 3))
                smooth = np.array([np.convolve(c, np.ones(k) / k, mode="valid") for c in curves])
                mean = smooth.mean(0)
                half = 1.96 * smooth.std(0, ddof=1) / np.sqrt(len(smooth)) if len(smooth) > 1 else 0 * mean
                x = np.arange(len(mean)) + k
                color = f"C{METHODS.index(m)}"
                ax.plot(x, mean, label=m, color=color, marker=".", lw=2 if m.endswith("-TDM") else 1.2)
                ax.fill_between(x, mean - half, mean + half, color=color, alpha=0.2)
            ax.set_ylabel("episode return" if key == "returns" else "contact events per episode")
            ax.grid(alpha=0.3)
            if row == 1:
                ax.set_xlabel("episode")
            if row == 0:
                ax.set_title(["SAC and AC: plain, -RP, -TDM", "-TDM vs safe-RL baselines"][col])
                ax.legend(fontsize=8)
    fig.suptitle("Maze (paper Fig. 9): mean over seeds with 95% confidence band (moving average)")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def tdm_overrides(args) -> dict:
    """The -TDM agents' keyword overrides from the command line (empty: the defaults)."""
    kw = {}
    if getattr(args, "tdm_refit_steps", None) is not None:
        if args.tdm_refit_steps < 1:
            raise SystemExit(f"skinsafe experiment maze: --tdm-refit-steps must be >= 1, got {args.tdm_refit_steps}")
        k = args.tdm_refit_steps
        kw["fit"] = {"steps": k, "min_steps": k, "batch_size": 64, "val_fraction": 0.1}
    if getattr(args, "tdm_unseen_max", None) is not None:
        if not 0 < args.tdm_unseen_max <= 1:
            raise SystemExit(f"skinsafe experiment maze: --tdm-unseen-max must lie in (0, 1], got {args.tdm_unseen_max}")
        kw["unseen_max"] = args.tdm_unseen_max
    if getattr(args, "tdm_prior_count", None) is not None:
        if not args.tdm_prior_count > 0:
            raise SystemExit(f"skinsafe experiment maze: --tdm-prior-count must be > 0, got {args.tdm_prior_count}")
        kw["prior_count"] = args.tdm_prior_count
    return kw


def config_from_args(args) -> dict:
    """Episodes, max steps and the evaluation seeds (a list; `seeds` is their number)."""
    cfg = dict(PRESETS[args.preset])
    for k in ("episodes", "max_steps"):
        if getattr(args, k, None) is not None:
            cfg[k] = getattr(args, k)
    if getattr(args, "seeds", None):
        cfg["eval_seeds"] = parse_seeds(args.seeds)
    else:
        cfg["eval_seeds"] = list(PROTOCOL["eval_seeds"]) if args.preset == "full" else list(range(cfg["seeds"]))
    cfg["seeds"] = len(cfg["eval_seeds"])
    if min(cfg["episodes"], cfg["max_steps"]) < 1:
        raise SystemExit(f"skinsafe experiment maze: episodes and max-steps must be >= 1, got {cfg}")
    return cfg


def run(args) -> int:
    cfg = config_from_args(args)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise SystemExit(f"skinsafe experiment maze: unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    extra = tdm_overrides(args)
    full = args.preset == "full"
    reps, stage_runs = [{"tuning": None}], {"tuning": []}
    if full:
        trials, n_reps = getattr(args, "trials", TRIALS), getattr(args, "replicates", REPLICATES)
        if trials < 1 or n_reps < 1:
            raise SystemExit(f"skinsafe experiment maze: --trials and --replicates must be >= 1, got {trials} and {n_reps}")
        first = parse_seeds(getattr(args, "tuning_seeds", None) or PROTOCOL["tuning_seeds"])
        span = first[-1] - first[0] + 1
        reps = [{"tuning_seeds": [s + r * span for s in first]} for r in range(n_reps)]
        overlap = sorted({s for r in reps for s in r["tuning_seeds"]} & set(cfg["eval_seeds"]))
        if overlap:
            raise SystemExit(f"skinsafe experiment maze: seeds {overlap} are both tuning and evaluation seeds (replicate r "
                             f"tunes on --tuning-seeds shifted by r x {span}); evaluate on held-out seeds (e.g. --tuning-seeds "
                             "0-1 --seeds 10-19)")
        n = min(getattr(args, "tuning_episodes", TUNING_EPISODES), cfg["episodes"])
        try:
            for r, rep in enumerate(reps):
                rep["tuning"], runs_r = tune(methods, dict(cfg, episodes=n), rep["tuning_seeds"], trials, out, args, extra, r)
                stage_runs["tuning"] += runs_r
        except BaseException:
            _stop_ray()  # tuning keeps its Ray for the next stage; a failed or interrupted run ends it
            raise
    for rep in reps:
        rep["chosen"] = {m: agent_kw(m, rep["tuning"][m]["chosen"] if rep["tuning"] else {}, cfg["episodes"], extra)
                         for m in methods}
    chosen = reps[0]["chosen"]
    eval_tasks = [_task(m, s, cfg, rep["chosen"][m]) for rep in reps for s in cfg["eval_seeds"] for m in methods]
    abl = []
    if full and not args.no_ablation:
        named = getattr(args, "ablation_seeds", None)
        abl_seeds = parse_seeds(named) if named else cfg["eval_seeds"][:PROTOCOL["ablation_seeds"]]
        if not set(abl_seeds) <= set(cfg["eval_seeds"]):
            raise SystemExit(f"skinsafe experiment maze: --ablation-seeds {abl_seeds} must be evaluation seeds ({cfg['eval_seeds']}): "
                             "each variant is compared with its method's evaluation runs")
        n = min(getattr(args, "ablation_episodes", ABLATION_EPISODES), cfg["episodes"])
        abl = ablation_tasks(chosen, methods, dict(cfg, episodes=n), abl_seeds)
    try:
        done = _run(eval_tasks + [t for _, t in abl], out, args, "maze evaluation" + (" + ablation" if abl else ""))
    finally:
        _stop_ray()
    per_rep = len(cfg["eval_seeds"]) * len(methods)
    rep_runs = [done[k * per_rep:(k + 1) * per_rep] for k in range(len(reps))]
    runs, abl_runs = rep_runs[0], done[len(eval_tasks):]
    stage_runs["evaluation"], stage_runs["ablation"] = [r for rr in rep_runs for r in rr], abl_runs
    for rep, rr in zip(reps, rep_runs):
        rep["summary"] = summarise(rr, methods, rep["tuning"])
    summary = dict(reps[0]["summary"])  # a copy: the replicates' own verdicts stay in `reps`
    if full:
        summary["claim"] = settle(summary["claim"], reps)
        summary["convergence"] = settle_convergence(summary["convergence"], reps)
    for m in methods:
        summary["methods"][m]["agent_kw"] = chosen[m]
    summary["config"] = {k: cfg[k] for k in ("seeds", "episodes", "max_steps")}
    summary["wall_seconds"] = time.perf_counter() - t0
    summary["task_seconds"] = float(sum(r["seconds"] for r in runs))
    summary["task_cpu_seconds"] = float(sum(r.get("cpu_seconds", np.nan) for r in runs))
    summary["stage_cpu_seconds"] = {k: float(sum(r.get("cpu_seconds", 0.0) for r in v)) for k, v in stage_runs.items() if v}
    per_seed = [run_row(r) for r in runs]
    ablation = ablation_rows(list(zip((h for h, _ in abl), abl_runs)), runs, chosen) if abl else []
    tuning = reps[0]["tuning"] or {}
    doc = {"summary": summary, "eval_seeds": cfg["eval_seeds"], "tuning": tuning, "per_seed": per_seed,
           "ablation": ablation, "runs": runs, "provenance": provenance()}
    if full:
        doc["replicates"] = [replicate_record(rep, rr) for rep, rr in zip(reps, rep_runs)]
        doc["verdict_agrees"] = summary["claim"]["verdict_agrees"]
    plot_curves(runs, methods, out / "maze_curves.png")
    md = markdown_table(summary, per_seed, tuning, ablation)
    atomic_write(out / "maze_contacts.md", md)
    atomic_write(out / "maze_results.json", json.dumps(doc, indent=1))
    print(md)
    print(f"wrote {out / 'maze_curves.png'}, {out / 'maze_contacts.md'}, {out / 'maze_results.json'} "
          f"({summary['wall_seconds']:.0f} s wall; CPU s in tasks: "
          + ", ".join(f"{k} {v:.0f}" for k, v in summary["stage_cpu_seconds"].items()) + ")")
    return 0
