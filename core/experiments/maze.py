"""`skinsafe experiment maze`: the strategy-layer experiment of the paper (Fig. 9) in the MuJoCo maze.

Trains every method (SAC, AC, each plain / -RP / -TDM, and the safe-RL baselines RRL, CPO, SQRL)
for several seeds, one Ray task per method x seed (`core.experiments.runner`: local Ray by default,
`--address` for a cluster, finished tasks reused by a restarted run). Writes into `--out`
(default `results/maze`): `maze_results.json` (per-method mean +- std total contacts and goal rates
over seeds, every run's per-episode returns, costs, goals and TDM fit records, and a `claim` computed
from the numbers), `maze_contacts.md` (the table) and `maze_curves.png` (return and cost curves
with 95% confidence bands).

Budgets: the maze has 72 (cell, heading) states and a 12-action shortest path; a random walk needs
a median ~500 macro-actions to reach the goal (20% within 200), so a run is 200 episodes of at most
200 macro-actions (`FULL`). `DEMO` is the demo's reduced run, `QUICK` the test suite's smoke run.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from skinsafe.core.experiments.runner import run_tasks
from skinsafe.core.skin.files import atomic_write

METHODS = ("SAC", "SAC-RP", "SAC-TDM", "AC", "AC-RP", "AC-TDM", "RRL", "CPO", "SQRL")
FULL = dict(seeds=5, episodes=200, max_steps=200)
DEMO = dict(seeds=2, episodes=60, max_steps=200)
QUICK = dict(seeds=1, episodes=2, max_steps=20)
LAST = 20  # episodes over which the final goal rate is measured
LEARNED_AT = 0.8  # a method "reaches the goal" when its goal rate over the last LAST episodes is at least this
# Relative CPU cost of one run (measured at the full budget), so the grid starts the longest first.
RUN_COST = {"SQRL": 5.0, "RRL": 5.0, "SAC-RP": 4.0, "SAC": 2.5, "CPO": 1.0, "SAC-TDM": 1.0, "AC-TDM": 1.0,
            "AC-RP": 0.4, "AC": 0.4}
PRESETS = {"full": FULL, "demo": DEMO, "quick": QUICK}


def add_arguments(p) -> None:
    p.add_argument("--out", default="results/maze", help="folder for the plots, table and JSON (default: %(default)s)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--full", action="store_const", dest="preset", const="full", help=f"the paper's budget (default): {FULL}")
    g.add_argument("--demo", action="store_const", dest="preset", const="demo", help=f"the demo's reduced run: {DEMO}")
    g.add_argument("--quick", action="store_const", dest="preset", const="quick", help=f"smoke test: {QUICK}")
    p.set_defaults(preset="full")
    p.add_argument("--seeds", type=int, help="seeds per method (overrides the preset)")
    p.add_argument("--episodes", type=int, help="training episodes per run (overrides the preset)")
    p.add_argument("--max-steps", type=int, help="macro-actions per episode (overrides the preset)")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of %(default)s")
    p.add_argument("--tdm-refit-steps", type=int, help="-TDM agents: gradient steps per periodic refit (default 25)")
    p.add_argument("--tdm-unseen-max", type=float, help="-TDM agents: most danger the filter gives an untried move (default 0.8)")
    p.add_argument("--tdm-prior-count", type=float,
                   help="-TDM agents: tries of a move after which the filter trusts the TDM's danger half-way (default 0.01)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every task instead of reusing finished ones")
    p.add_argument("--no-progress", action="store_true")


def run_one(method: str, seed: int, episodes: int, max_steps: int, agent_kw: dict | None = None) -> dict:
    """Train one method with one seed; per-episode returns, contact events (costs), goals and lengths.
    `agent_kw` overrides the agent's keyword arguments (`make_agent`); a TDM `fit` is a FitConfig dict."""
    import torch

    from skinsafe.core.learn.baselines import make_agent
    from skinsafe.core.learn.maze_env import MazeEnv, MazeFeatures
    from skinsafe.core.learn.tdm_training import FitConfig

    torch.set_num_threads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    env = MazeEnv(max_steps=max_steps)
    kw = dict(agent_kw or {})
    if "fit" in kw:
        kw["fit"] = FitConfig(**kw["fit"])
    agent = make_agent(method, 4, env.action_space.n, env.n_taxels, MazeFeatures(env.walls), seed=seed, **kw)
    returns, costs, goals, steps = [], [], [], []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed * 100003 + ep)
        ret = cost = 0.0
        n = 0
        while True:
            a = agent.act(obs)
            nxt, r, term, trunc, info = env.step(a)
            agent.observe(obs, a, r, info["cost"], info["taxel_danger"], nxt, term, trunc)
            obs, ret, cost, n = nxt, ret + r, cost + info["cost"], n + 1
            if term or trunc:
                break
        agent.end_episode()
        returns.append(ret)
        costs.append(cost)
        goals.append(bool(term))
        steps.append(n)
    stats = agent.stats()
    stats.get("tdm", {}).pop("last", None)  # the fit records go in whole (thinned) below
    fits = agent.shield.trainer.history if agent.shield is not None else []
    return {"method": method, "seed": seed, "returns": returns, "costs": costs, "goals": goals, "steps": steps,
            "stats": stats, "tdm_fits": _thin(fits), "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0}


def _thin(fits: list[dict], keep: int = 60) -> list[dict]:
    """At most `keep` fit records, evenly spread (the result file stays small)."""
    if len(fits) <= keep:
        return fits
    return [fits[int(i)] for i in np.linspace(0, len(fits) - 1, keep)]


def _mean_std(x) -> tuple[float, float]:
    x = np.asarray(x, float)
    return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0


def summarise(runs: list[dict], methods: list[str]) -> dict:
    """Per-method totals and goal rates (mean and std over seeds) and the claim check."""
    rows = {}
    for m in methods:
        rs = [r for r in runs if r["method"] == m]
        tot = _mean_std([sum(r["costs"]) for r in rs])
        rate = _mean_std([np.mean(r["goals"]) for r in rs])
        last = _mean_std([np.mean(r["goals"][-LAST:]) for r in rs])
        rows[m] = {"total_contacts_mean": tot[0], "total_contacts_std": tot[1],
                   "goal_rate_mean": rate[0], "goal_rate_std": rate[1],
                   "goal_rate_last_mean": last[0], "goal_rate_last_std": last[1],
                   "mean_return": float(np.mean([np.mean(r["returns"]) for r in rs])),
                   "mean_steps": float(np.mean([np.mean(r["steps"]) for r in rs])),
                   "seconds_mean": float(np.mean([r.get("seconds", np.nan) for r in rs])), "seeds": len(rs)}
    return {"methods": rows, "claim": claim_check(rows)}


def claim_check(rows: dict, learned_at: float = LEARNED_AT) -> dict:
    """The paper's claim (Fig. 9b): the -TDM variants have the lowest total contact events (means over
    seeds). `learned` says whether SAC and AC (and their -TDM variants) reach the goal in at least
    `learned_at` of the last episodes: without that, the comparison says little."""
    tdm = {m: v["total_contacts_mean"] for m, v in rows.items() if m.endswith("-TDM")}
    other = {m: v["total_contacts_mean"] for m, v in rows.items() if not m.endswith("-TDM")}
    if not tdm or not other:
        return {"holds": None, "statement": "needs at least one -TDM method and one other method"}
    best_tdm, best_other = min(tdm, key=tdm.get), min(other, key=other.get)
    worst_tdm = max(tdm, key=tdm.get)
    holds = tdm[worst_tdm] < other[best_other]
    ratio = other[best_other] / tdm[best_tdm] if tdm[best_tdm] > 0 else float("inf")
    learners = [m for m in ("SAC", "AC", "SAC-TDM", "AC-TDM") if m in rows and "goal_rate_last_mean" in rows[m]]
    learned = {m: rows[m]["goal_rate_last_mean"] >= learned_at for m in learners}
    own = []
    for m, v in tdm.items():
        base = m[:-4]
        if base in other and other[base] > 0:
            own.append(f"{m} has {100 * (1 - v / other[base]):.0f}% fewer contacts than {base}")
    if holds:
        s = (f"The paper's claim holds: every -TDM variant has fewer total contacts than every other method; the best, "
             f"{best_tdm} ({tdm[best_tdm]:.1f}), is {ratio:.2f}x lower than the best other method, {best_other} "
             f"({other[best_other]:.1f}).")
    else:
        lower = sorted((m for m in other if other[m] <= tdm[worst_tdm]), key=other.get)
        rate = {m: rows[m].get("goal_rate_last_mean") for m in lower}
        lower = [f"{m} (goal rate {rate[m]:.2f} over the last {LAST} episodes)" if rate[m] is not None else m for m in lower]
        s = (f"The paper's claim does not hold here: {', '.join(lower)} had no more total contacts than {worst_tdm} "
             f"({tdm[worst_tdm]:.1f}); best -TDM {best_tdm} {tdm[best_tdm]:.1f} vs best other {best_other} "
             f"{other[best_other]:.1f} (ratio other/TDM {ratio:.2f}).")
    if own:
        s += " " + "; ".join(own) + "."
    # The same comparison among the methods that learned the task (goal rate over the last episodes >=
    # learned_at): a method that never reaches the goal can touch little by hardly moving on.
    reach = {m for m, v in rows.items() if v.get("goal_rate_last_mean") is not None and v["goal_rate_last_mean"] >= learned_at}
    tdm_r = {m: v for m, v in tdm.items() if m in reach}
    other_r = {m: v for m, v in other.items() if m in reach}
    holds_r = None
    if tdm_r and other_r:
        w, b = max(tdm_r, key=tdm_r.get), min(other_r, key=other_r.get)
        holds_r = tdm_r[w] < other_r[b]
        s += (f" Among the methods that reach the goal in >= {learned_at:.0%} of the last {LAST} episodes "
              f"({', '.join(sorted(reach))}) the claim {'holds' if holds_r else 'does not hold'}: worst -TDM {w} "
              f"{tdm_r[w]:.1f} vs best other {b} {other_r[b]:.1f}.")
    if learned:
        bad = [m for m, ok in learned.items() if not ok]
        s += (f" Learning: {', '.join(learned)} reach the goal in >= {learned_at:.0%} of the last {LAST} episodes."
              if not bad else f" Learning: {', '.join(bad)} reach{'es' if len(bad) == 1 else ''} the goal in fewer than {learned_at:.0%} of the last "
              f"{LAST} episodes, so this budget does not show the trained behaviour of the paper.")
    return {"holds": bool(holds), "holds_among_goal_reaching": holds_r, "best_tdm": best_tdm, "best_other": best_other, "ratio_best_other_to_best_tdm": ratio,
            "learned": learned, "all_learned": bool(learned) and all(learned.values()), "statement": s}


def markdown_table(summary: dict) -> str:
    lines = ["| method | total contact events (mean ± std over seeds) | goal rate | goal rate, last 20 episodes | "
             "mean episode return | seeds |", "| --- | --- | --- | --- | --- | --- |"]
    for m, v in summary["methods"].items():
        lines.append(f"| {m} | {v['total_contacts_mean']:.1f} ± {v['total_contacts_std']:.1f} | "
                     f"{v['goal_rate_mean']:.2f} ± {v['goal_rate_std']:.2f} | {v['goal_rate_last_mean']:.2f} ± "
                     f"{v['goal_rate_last_std']:.2f} | {v['mean_return']:.1f} | {v['seeds']} |")
    return "\n".join(lines) + "\n\n" + summary["claim"]["statement"] + "\n"


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
    cfg = dict(PRESETS[args.preset])
    for k in ("seeds", "episodes", "max_steps"):
        if getattr(args, k) is not None:
            cfg[k] = getattr(args, k)
    if min(cfg.values()) < 1:
        raise SystemExit(f"skinsafe experiment maze: seeds, episodes and max-steps must be >= 1, got {cfg}")
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
    tasks = [{"method": m, "seed": s, "episodes": cfg["episodes"], "max_steps": cfg["max_steps"]}
             for s in range(cfg["seeds"]) for m in methods]
    agent_kw = tdm_overrides(args)
    for t in tasks:
        if agent_kw and t["method"].endswith("-TDM"):
            t["agent_kw"] = agent_kw
    runs = run_tasks(run_one, tasks, out / "tasks", address=args.address, workers=args.workers,
                     progress=not args.no_progress, desc="maze runs", fresh=args.fresh,
                     cost=lambda t: RUN_COST[t["method"]] * t["episodes"] * t["max_steps"])
    summary = summarise(runs, methods)
    summary["config"] = cfg
    summary["wall_seconds"] = time.perf_counter() - t0
    summary["task_seconds"] = float(sum(r["seconds"] for r in runs))
    summary["task_cpu_seconds"] = float(sum(r.get("cpu_seconds", np.nan) for r in runs))
    plot_curves(runs, methods, out / "maze_curves.png")
    atomic_write(out / "maze_contacts.md", markdown_table(summary))
    atomic_write(out / "maze_results.json", json.dumps({"summary": summary, "runs": runs}, indent=1))
    print(markdown_table(summary))
    print(f"wrote {out / 'maze_curves.png'}, {out / 'maze_contacts.md'}, {out / 'maze_results.json'} "
          f"({summary['wall_seconds']:.0f} s wall, {summary['task_seconds']:.0f} s in tasks)")
    return 0
