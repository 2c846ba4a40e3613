"""The demo report's plots, drawn from the results files the stages write (the same JSON the
README's figures come from). Each function returns a matplotlib Figure whose every panel has a
title and axis labels with units; bands never leave the range the seeds span (a mean ± 95%
band is drawn only from 3 seeds up, fewer are drawn one line per seed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from skinsafe.core.skin.files import write_png

SCENE_DT = 0.01  # s: the desk and collaboration scenes' control period (their traces are one value per tick)
LABELS = {"vanilla": "no modulation", "tdm": "TDM modulation", "tdm2": "2-step TDM modulation"}
BASELINES = ("RRL", "CPO", "SQRL")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Path) -> Path:
    """PNG through a temporary file, cropped to what is drawn (no label cut off at the edge)."""
    return write_png(fig, path, bbox_inches="tight")


def _smooth(y: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or y.shape[-1] < window:
        return y
    k = np.ones(window) / window
    return np.apply_along_axis(lambda r: np.convolve(r, k, mode="valid"), -1, y)


def plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def seed_lines(ax, x, per_seed: np.ndarray, color, label: str, marker: str = "") -> None:
    """Per-seed curves (seeds, T): one thin line per seed below 3 seeds; from 3 on the mean and a
    95% band (t-interval) clipped to the range the seeds span."""
    per_seed = np.atleast_2d(per_seed)
    n = len(per_seed)
    if n < 3:
        for k, y in enumerate(per_seed):
            (line,) = ax.plot(x, y, marker=marker, color=color, lw=1.2, ls="-" if k == 0 else "--",
                              label=f"{label} (seed {k})" if n > 1 else label)
            color = line.get_color()
        return
    mean = per_seed.mean(0)
    t = {3: 4.30, 4: 3.18, 5: 2.78}.get(n, 2.0)  # Student t, 95%, n - 1 degrees of freedom
    half = t * per_seed.std(0, ddof=1) / np.sqrt(n)
    lo, hi = np.maximum(mean - half, per_seed.min(0)), np.minimum(mean + half, per_seed.max(0))
    (line,) = ax.plot(x, mean, marker=marker, color=color, lw=1.5, label=label)
    ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2, lw=0)


def _maze_series(runs: list[dict], method: str, key: str) -> np.ndarray:
    return np.array([r[key] for r in sorted(runs, key=lambda r: r["seed"]) if r["method"] == method], float)


def maze(results: dict, grid: dict | None = None, window: int = 5):
    """Return and contact events per episode of a maze run, and the -TDM variants against the
    safe-RL baselines (cumulative contacts) from `grid` (the full grid) when the run has no baselines."""
    plt = _plt()
    rep = results["replicates"][0]
    summary, runs = rep["summary"], rep["runs"]
    methods = list(summary["methods"])
    cfg = {"seeds": len(results["eval_seeds"]), "episodes": results["evaluation_conditions"]["episodes"]}
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    every = list(dict.fromkeys(methods + list((grid or results)["replicates"][0]["summary"]["methods"])))
    colors = dict(zip(every, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 3))
    budget = f"{plural(cfg['seeds'], 'seed')} x {plural(cfg['episodes'], 'episode')}"
    for ax, key, ylabel in ((axes[0], "returns", "episode return (points; +100 at the goal)"),
                            (axes[1], "costs", "contact events per episode (count)")):
        for m in methods:
            y = _smooth(_maze_series(runs, m, key), window)
            seed_lines(ax, np.arange(y.shape[-1]) + window, y, colors[m], m)
        ax.set_xlabel("episode (number)")
        ax.set_ylabel(ylabel + (f", mean of {window}" if window > 1 else ""))
        ax.legend(fontsize=7)
    axes[0].set_title(f"Return per episode ({budget})")
    axes[1].set_title(f"Contact events per episode ({budget})")
    src, src_budget = rep, budget
    if not any(b in methods for b in BASELINES) and grid is not None:
        src = grid["replicates"][0]
        src_budget = (f"full grid, replicate 1, {len(grid['eval_seeds'])} seeds x "
                      f"{grid['evaluation_conditions']['episodes']} episodes")
    ax = axes[2]
    shown = [m for m in src["summary"]["methods"] if m.endswith("-TDM") or m in BASELINES]
    for m in shown:
        y = np.cumsum(_maze_series(src["runs"], m, "costs"), axis=-1)
        seed_lines(ax, np.arange(1, y.shape[-1] + 1), y, colors[m], m)
    ax.set_yscale("symlog", linthresh=10)  # -TDM's tens and CPO's hundreds on one axis
    ax.set_xlabel("episode (number)")
    ax.set_ylabel("contact events so far (count, log scale above 10)")
    ax.set_title(f"-TDM vs safe-RL baselines ({src_budget})")
    ax.legend(fontsize=7)
    fig.suptitle("Maze (paper Fig. 9): " + ("mean over seeds, 95% band" if cfg["seeds"] >= 3 else "one line per seed"))
    fig.tight_layout()
    return fig


def tracking_contacts(res: dict):
    """Contact ticks per episode per method (tracking.json)."""
    plt = _plt()
    from matplotlib.ticker import MaxNLocator

    cfg = res["config"]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for method, by_seed in res["runs"].items():
        c = np.array([[r["contacts"] for r in rows] for rows in by_seed.values()], float)
        seed_lines(ax, np.arange(1, c.shape[1] + 1), c, None, LABELS.get(method, method), marker="o")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("episode (number; the TDM is re-trained after each)")
    ax.set_ylabel(f"contact ticks per episode (count of {cfg['control_dt'] * 1e3:.0f} ms ticks)")
    ax.set_title(f"UR5 tracking among balls (Fig. 11): {plural(len(next(iter(res['runs'].values()))), 'seed')} x "
                 f"{plural(cfg['episodes'], 'episode')}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def tracking_paths(res: dict):
    """The last episode's end-effector path per method in 3-D, with the desired path, the balls
    and the skin's contact points (first seed)."""
    plt = _plt()
    seed = next(iter(res["balls"]))
    methods = list(res["last"])
    fig = plt.figure(figsize=(5.2 * len(methods), 4.8))
    for i, method in enumerate(methods):
        ep = res["last"][method][seed]
        ax = fig.add_subplot(1, len(methods), i + 1, projection="3d")
        ax.plot(*np.array(ep["ee_desired"]).T, "k--", lw=1, label="desired path")
        ax.plot(*np.array(ep["ee"]).T, color="tab:blue", lw=1.5, label="end effector")
        if len(ep["contact_points"]):
            ax.scatter(*np.array(ep["contact_points"]).T, color="tab:green", s=8, label="skin contact points")
        for k, c in enumerate(res["balls"][seed]):
            ax.scatter(*c, color="tab:orange", s=120, alpha=0.6, label="ball" if k == 0 else None)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
        ax.set_title(f"{LABELS.get(method, method)}: {ep['contacts']} contact ticks", fontsize=10)
        ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Last episode ({res['config']['episodes']}) of seed {seed}: world frame, UR5 base at the origin")
    return fig


def desk(res: dict):
    """Arm-desk clearance over time per stack (desk.json, Fig. 14)."""
    plt = _plt()
    dt = res.get("control_dt", SCENE_DT)
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for name, r in res["runs"].items():
        y = np.array(r["clearance_mm"])
        ax.plot(np.arange(len(y)) * dt, y, label=f"{name}: min {r['min_clearance_mm']:+.1f} mm")
    ax.axhline(0, color="k", lw=0.8)
    ax.text(0, 0, " touching the desk", va="bottom", fontsize=7)
    ax.set_xlabel("time (s; the touch at 0.1-0.2 s)")
    ax.set_ylabel("arm-desk clearance (mm)")
    ax.set_title(f"Fig. 14: retraction toward a desk ({len(y) * dt:.1f} s)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def collaboration(res: dict):
    """Force on the person per scenario and stack, each contact's and sweep cell's worst ratio to its
    ISO/TS 15066 limits (collaboration.json, Fig. 15): the experiment's own figure."""
    from skinsafe.core.experiments.collaboration_result import plot

    _plt()
    return plot(res)


def poke_force(res: dict):
    """Retraction distance against peak poke force, with the least-squares line and alpha/12 (Fig. 8/12)."""
    plt = _plt()
    fs, alpha = res["force_sweep"], res["params"]["alpha"]
    f, d = np.array(fs["force"]), np.array(fs["distance"]) * 100
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(f, d, "o", label="measured (MuJoCo)")
    xs = np.linspace(0, f.max() * 1.05, 50)
    ax.plot(xs, (fs["slope"] * xs + fs["intercept"]) * 100, "-", label=f"fit: {fs['slope'] * 100:.4f} cm/N, "
                                                                       f"R² {fs['r2']:.5f}")
    ax.plot(xs, alpha / 12 * xs * 100, ":", label=f"eq. 10: α/12 = {alpha / 12 * 100:.4f} cm/N")
    ax.set_xlabel("peak force on the taxel (N)")
    ax.set_ylabel("retraction distance (cm)")
    ax.set_title(f"Fig. 8/12: retraction vs poke force ({len(f)} pokes, taxel {fs['taxel']} on {fs['body']})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def poke_multicontact(res: dict):
    """Fig. 7: each contact's achieved share of its own eq. 10 distance, per merge and contact count."""
    plt = _plt()
    rows = res["multicontact"]
    counts = sorted({r["contacts"] for r in rows})
    fig, axes = plt.subplots(1, len(counts), figsize=(7 * len(counts), 4), squeeze=False)
    for ax, n in zip(axes[0], counts):
        sub = [r for r in rows if r["contacts"] == n]
        x = np.arange(len(sub))
        ax.bar(x - 0.2, [r["dominant_fraction"] for r in sub], 0.4, label="dominant (highest priority)")
        ax.bar(x + 0.2, [np.mean(r["others_fraction"]) for r in sub], 0.4, label="the others (mean)")
        ax.axhline(1, color="k", lw=0.8)
        ax.set_xticks(x, [f"{r['merge']}\nε = {r['epsilon']:g}\n{r['into_contact_mm']:.1f} mm in" for r in sub],
                      fontsize=8)
        ax.set_xlabel("merge, ε, and the worst displacement of a contacted taxel into its contact (mm)")
        ax.set_ylabel("achieved / own eq. 10 distance (ratio)")
        ax.set_title(f"{n} contacts at {', '.join(f'{f:g}' for f in sub[0]['forces'])} N")
        ax.legend(fontsize=7)
    fig.suptitle("Fig. 7: lower priorities against the dominant retraction (1 = as if alone)")
    fig.tight_layout()
    return fig
