"""`skinsafe experiment maze`: the strategy-layer experiment of the paper (Fig. 9) in the MuJoCo maze.

Trains every method (SAC, AC, each plain / -RP / -TDM, and the safe-RL baselines RRL, CPO, SQRL)
for several seeds, then writes return and cost curves with 95% confidence bands (PNG), the total
contact events per method (markdown and JSON) and whether the -TDM variants have the lowest totals.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from skinsafe.core.skin.files import atomic_write

METHODS = ("SAC", "SAC-RP", "SAC-TDM", "AC", "AC-RP", "AC-TDM", "RRL", "CPO", "SQRL")
FULL = dict(seeds=5, episodes=20, max_steps=80)
QUICK = dict(seeds=2, episodes=3, max_steps=25)


def add_arguments(p) -> None:
    p.add_argument("--out", default="maze_results", help="folder for the plots, table and JSON (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help=f"reduced configuration for tests: {QUICK}")
    p.add_argument("--seeds", type=int, help=f"seeds per method (default {FULL['seeds']})")
    p.add_argument("--episodes", type=int, help=f"training episodes per run (default {FULL['episodes']})")
    p.add_argument("--max-steps", type=int, help=f"macro-actions per episode (default {FULL['max_steps']})")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of %(default)s")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes (default %(default)s)")


def run_one(method: str, seed: int, episodes: int, max_steps: int) -> dict:
    """Train one method with one seed; per-episode returns and contact events (costs)."""
    import torch

    from skinsafe.core.learn.baselines import make_agent
    from skinsafe.core.learn.maze_env import MazeEnv, MazeFeatures

    torch.set_num_threads(1)
    env = MazeEnv(max_steps=max_steps)
    agent = make_agent(method, 4, env.action_space.n, env.n_taxels, MazeFeatures(env.walls), seed=seed)
    returns, costs, goals = [], [], 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed * 100003 + ep)
        ret = cost = 0.0
        while True:
            a = agent.act(obs)
            nxt, r, term, trunc, info = env.step(a)
            agent.observe(obs, a, r, info["cost"], info["taxel_danger"], nxt, term, trunc)
            obs, ret, cost = nxt, ret + r, cost + info["cost"]
            if term or trunc:
                goals += int(term)
                break
        agent.end_episode()
        returns.append(ret)
        costs.append(cost)
    return {"method": method, "seed": seed, "returns": returns, "costs": costs, "goals": goals}


def _star(args):
    return run_one(*args)


def summarise(runs: list[dict], methods: list[str]) -> dict:
    """Per-method totals (mean and std over seeds) and the claim check."""
    rows = {}
    for m in methods:
        rs = [r for r in runs if r["method"] == m]
        tot = np.array([sum(r["costs"]) for r in rs], float)
        ret = np.array([np.mean(r["returns"]) for r in rs], float)
        rows[m] = {"total_contacts_mean": float(tot.mean()), "total_contacts_std": float(tot.std(ddof=1)) if len(tot) > 1 else 0.0,
                   "mean_return": float(ret.mean()), "goal_rate": float(np.mean([r["goals"] / len(r["returns"]) for r in rs])),
                   "seeds": len(rs)}
    return {"methods": rows, "claim": claim_check(rows)}


def claim_check(rows: dict) -> dict:
    """Do the -TDM variants have the lowest total contact events? Compared by mean over seeds."""
    tdm = {m: v["total_contacts_mean"] for m, v in rows.items() if m.endswith("-TDM")}
    other = {m: v["total_contacts_mean"] for m, v in rows.items() if not m.endswith("-TDM")}
    if not tdm or not other:
        return {"holds": None, "statement": "needs at least one -TDM method and one other method"}
    best_tdm, best_other = min(tdm, key=tdm.get), min(other, key=other.get)
    worst_tdm = max(tdm, key=tdm.get)
    holds = tdm[worst_tdm] < other[best_other]
    ratio = other[best_other] / tdm[best_tdm] if tdm[best_tdm] > 0 else float("inf")
    own = []
    for m, v in tdm.items():
        base = m[:-4]
        if base in other and other[base] > 0:
            own.append(f"{m} has {100 * (1 - v / other[base]):.0f}% fewer contacts than {base}")
    if holds:
        s = (f"Agrees with the paper: every -TDM variant has fewer total contacts than every other method; the best, "
             f"{best_tdm} ({tdm[best_tdm]:.1f}), is {ratio:.2f}x lower than the best other method, {best_other} "
             f"({other[best_other]:.1f}).")
    else:
        lower = sorted((m for m in other if other[m] <= tdm[worst_tdm]), key=other.get)
        s = (f"Does not fully agree with the paper: {', '.join(lower)} had no more total contacts than {worst_tdm} "
             f"({tdm[worst_tdm]:.1f}); best -TDM {best_tdm} {tdm[best_tdm]:.1f} vs best other {best_other} "
             f"{other[best_other]:.1f} (ratio other/TDM {ratio:.2f}).")
    if own:
        s += " " + "; ".join(own) + "."
    return {"holds": bool(holds), "best_tdm": best_tdm, "best_other": best_other, "ratio_best_other_to_best_tdm": ratio,
            "statement": s}


def markdown_table(summary: dict) -> str:
    lines = ["| method | total contact events (mean ± std over seeds) | mean episode return | goal rate | seeds |",
             "| --- | --- | --- | --- | --- |"]
    for m, v in summary["methods"].items():
        lines.append(f"| {m} | {v['total_contacts_mean']:.1f} ± {v['total_contacts_std']:.1f} | {v['mean_return']:.1f} | "
                     f"{v['goal_rate']:.2f} | {v['seeds']} |")
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


def run(args) -> int:
    cfg = dict(QUICK if args.quick else FULL)
    for k in ("seeds", "episodes", "max_steps"):
        if getattr(args, k) is not None:
            cfg[k] = getattr(args, k)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise SystemExit(f"skinsafe experiment maze: unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    if min(cfg.values()) < 1:
        raise SystemExit(f"skinsafe experiment maze: seeds, episodes and max-steps must be >= 1, got {cfg}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [(m, s, cfg["episodes"], cfg["max_steps"]) for s in range(cfg["seeds"]) for m in methods]
    bar = tqdm(total=len(tasks), desc="maze runs")
    runs = []
    if args.jobs > 1:
        with mp.get_context("spawn").Pool(args.jobs) as pool:
            for r in pool.imap_unordered(_star, tasks):
                runs.append(r)
                bar.update()
    else:
        for t in tasks:
            runs.append(_star(t))
            bar.update()
    bar.close()
    runs.sort(key=lambda r: (methods.index(r["method"]), r["seed"]))
    summary = summarise(runs, methods)
    summary["config"] = cfg
    plot_curves(runs, methods, out / "maze_curves.png")
    atomic_write(out / "maze_contacts.md", markdown_table(summary))
    atomic_write(out / "maze_results.json", json.dumps({"summary": summary, "runs": runs}, indent=1))
    print(markdown_table(summary))
    print(f"wrote {out / 'maze_curves.png'}, {out / 'maze_contacts.md'}, {out / 'maze_results.json'}")
    return 0
