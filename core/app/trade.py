"""`skinsafe trade`: speed against accuracy for the knobs users turn, swept in parallel with Ray.

Each knob is swept over a few values; every point is one Ray task that measures its speed
(median wall time of its unit of work) and returns what it computed. The error of a point is
measured against the knob's most accurate setting (the reference, error 0, speedup 1):

- `density`, the sample skin's pitch (m): readout + all taxels' Jacobians per control tick;
  contact localisation (force-weighted centroid of the lit taxels) vs the densest skin, mm.
- `timestep`, MuJoCo's timestep (s): wall ms per simulated second; taxel forces vs the
  smallest timestep (relative L1, median over samples).
- `collision`, `SceneOptions.collision` (+ target faces): physics step; taxel forces vs the
  full mesh (relative L1).
- `sensing`, the readout model: physics step + readout; taxel forces vs per-taxel MuJoCo
  touch sensors (relative L1, median).
- `nstep`, Monte Carlo rollouts per (s, a) of eq. 8: the targets of a batch of states; RMS of
  w vs the most samples.
- `damping`, the DLS damping: one defensiveness tick; the taxel path vs the undamped inverse,
  max mm.

For `damping` the trade is accuracy against the peak joint speed the retraction asks for near
the UR5 elbow singularity (compute time hardly changes): its Pareto front uses `peak_qdot`.
Every other knob's front uses `ms`. Outputs in `--out`: `trade.png` (one panel per knob, error
against speedup or peak joint speed, Pareto points filled), `trade.md` and `trade.json`.

Ray: `--address` joins an existing cluster (`auto` for one started with `ray start` on this
machine; every node needs skinsafe installed); without it a new local Ray starts by itself and
stops at the end.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from skinsafe.core.app.knobs import KNOBS
from skinsafe.core.skin.files import atomic_write, write_png

# --- Pareto front ---------------------------------------------------------------------------

def pareto_front(cost, error) -> np.ndarray:
    """(K,) True where no other point is at least as good in both (lower cost, lower error) and
    strictly better in one. Equal points are all on the front."""
    c, e = np.asarray(cost, float), np.asarray(error, float)
    if c.shape != e.shape or c.ndim != 1:
        raise ValueError(f"pareto_front: cost {c.shape} and error {e.shape} must be 1-D of the same length")
    le = (c[None, :] <= c[:, None]) & (e[None, :] <= e[:, None])
    lt = (c[None, :] < c[:, None]) | (e[None, :] < e[:, None])
    return ~(le & lt).any(axis=1)


# --- the sweep --------------------------------------------------------------------------------

def _task(knob: str, value, quick: bool, where: str | None = None) -> dict:
    """One sweep point (runs in a Ray worker)."""
    return KNOBS[knob].point(value, quick, where)


def parse_knobs(text: str | list | tuple, where: str | None = None) -> list[str]:
    names = [k.strip() for k in text.split(",")] if isinstance(text, str) else list(text)
    names = [k for k in names if k]
    bad = [k for k in names if k not in KNOBS]
    if bad or not names:
        raise ValueError(f"knobs {bad or '(none)'} unknown; choose from {', '.join(KNOBS)} (comma-separated)")
    ur5 = [k for k in names if not KNOBS[k].any_robot]
    if where is not None and ur5:
        raise ValueError(f"knob '{ur5[0]}' sweeps the built-in UR5 only (not the robot of {where}); choose from "
                         f"{', '.join(k for k in KNOBS if KNOBS[k].any_robot)}")
    return list(dict.fromkeys(names))


def rows_from_results(results: dict[tuple[str, object], dict], knobs: list[str], quick: bool,
                      where: str | None = None) -> list[dict]:
    """Flat rows (one per point, knob by knob in sweep order) with errors, speedups and Pareto flags."""
    rows = []
    for name in knobs:
        knob = KNOBS[name]
        values = knob.sweep(quick, where)
        ref = results[(name, values[0])]
        mine = []
        for v in values:
            r = results[(name, v)]
            extras = {k: x for k, x in r.items() if k not in ("ms", "unit", "out")}
            mine.append({"knob": name, "value": v, "ms": r["ms"], "unit": r["unit"],
                         "speedup_vs_reference": ref["ms"] / r["ms"],
                         "error": 0.0 if v == values[0] else knob.error(r["out"], ref["out"]),
                         "error_metric": knob.error_metric, "pareto": False, **extras})
        flags = pareto_front([r[knob.cost] for r in mine], [r["error"] for r in mine])
        for r, f in zip(mine, flags):
            r["pareto"] = bool(f)
        rows += mine
    return rows


def run_sweep(knobs=tuple(KNOBS), quick: bool = False, address: str | None = None, out: str | Path | None = "out/trade",
              progress: bool = True, where: str | Path | None = None) -> list[dict]:
    """Sweep the knobs as Ray tasks (one per point) and return the rows; with `out`, also write
    `trade.png`, `trade.md` and `trade.json` there. `where`: a taxel map (any robot; default the UR5
    sample skin). Joins the cluster at `address`, else starts a local Ray (and stops it at the
    end) unless one is already initialised in this process."""
    import ray
    from tqdm import tqdm

    where = None if where is None else str(Path(where).resolve())
    names = parse_knobs(knobs, where)
    if where is not None:  # refuse a bad map here, before any worker starts
        from skinsafe.core.app.knob_skins import skin_of

        skin_of(where)
    started = not ray.is_initialized()
    if started:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            # "local": a new Ray of our own, even where `ray start` left a cluster on this machine
            ray.init(address="local", include_dashboard=False, log_to_driver=False,
                     object_store_memory=256 * 2 ** 20)
    try:
        task = ray.remote(num_cpus=1)(_task)
        points = [(n, v) for n in names for v in KNOBS[n].sweep(quick, where)]
        refs = {task.remote(n, v, quick, where): (n, v) for n, v in points}
        results: dict = {}
        pending = list(refs)
        with tqdm(total=len(pending), desc="trade sweep", disable=not progress, file=sys.stderr) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    key = refs[ref]
                    results[key] = ray.get(ref)
                    bar.set_postfix_str(f"{key[0]}={key[1]}")
                    bar.update()
    finally:
        if started:
            ray.shutdown()
    rows = rows_from_results(results, names, quick, where)
    if out is not None:
        write_outputs(rows, Path(out))
    return rows


# --- outputs ----------------------------------------------------------------------------------

CORE = ("knob", "value", "ms", "unit", "speedup_vs_reference", "error", "error_metric", "pareto")


def markdown(rows: list[dict]) -> str:
    """The rows as a markdown table; per-knob extra columns go into `details`."""
    def fmt(v):
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(CORE) + " | details |", "|" + " --- |" * (len(CORE) + 1)]
    for r in rows:
        details = ", ".join(f"{k}={fmt(v)}" for k, v in r.items() if k not in CORE)
        lines.append("| " + " | ".join(fmt(r[k]) for k in CORE) + f" | {details} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path, title: str = "Speed vs accuracy: each knob against its most accurate setting"
         ) -> Path:
    """One panel per knob: error against speedup (or peak joint speed), Pareto points filled;
    long labels wrapped and the picture cropped to what is drawn, so nothing is cut off."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import ScalarFormatter

    knobs = list(dict.fromkeys(r["knob"] for r in rows))
    cols = min(3, len(knobs))
    nrows = int(np.ceil(len(knobs) / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 4.2 * nrows), squeeze=False)
    for ax, name in zip(axes.ravel(), knobs):
        mine = [r for r in rows if r["knob"] == name]
        peak = KNOBS[name].cost == "peak_qdot"
        x = np.array([r["peak_qdot"] if peak else r["speedup_vs_reference"] for r in mine])
        y = np.array([r["error"] for r in mine])
        front = np.array([r["pareto"] for r in mine])
        ax.plot(x[~front], y[~front], "o", mfc="none", color="C0", label="dominated")
        order = np.argsort(x[front])
        ax.plot(x[front][order], y[front][order], "o-", color="C3", label="Pareto-optimal")
        for xi, yi, r in zip(x, y, mine):
            ax.annotate(str(r["value"]), (xi, yi), fontsize=7, xytext=(3, 3), textcoords="offset points")
        if x.max() / x.min() > 5:
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.margins(x=0.15, y=0.12)  # room for the point labels inside the panel
        ax.set_xlabel("peak joint speed asked (rad/s; lower is safer)" if peak else
                      f"speedup vs reference (x, per {mine[0]['unit']})")
        ax.set_ylabel("\n".join(textwrap.wrap(f"error: {mine[0]['error_metric']}", 42)), fontsize=8)
        ax.set_title(f"{name} (reference {mine[0]['value']})")
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(knobs):]:
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    return write_png(fig, path, dpi=100, bbox_inches="tight")


def write_outputs(rows: list[dict], out: Path) -> list[Path]:
    return [plot(rows, out / "trade.png"), atomic_write(out / "trade.md", markdown(rows)),
            atomic_write(out / "trade.json", json.dumps(rows, indent=1))]


# --- CLI ----------------------------------------------------------------------------------------

def design_first(args) -> str:
    """`--robot`: a skin designed from `--layout` (as `skinsafe design` does), saved in `--out`."""
    from skinsafe.core.app import design
    from skinsafe.core.robot.catalog import DESCRIPTIONS, description
    from skinsafe.core.skin.model import DesignError

    robot, dirs, xargs = args.robot, list(args.package_dir), list(args.xacro_arg)
    if robot in DESCRIPTIONS:  # a bundled or fetched description by name
        try:
            ref = description(robot)
        except DesignError as e:
            raise SystemExit(f"skinsafe trade: {e}") from None
        robot, dirs = ref.path, dirs or list(ref.package_dirs)
        xargs = [f"{k}:={v}" for k, v in ref.xacro_args.items()] + xargs
    out = Path(args.out) / "skin.json"
    parser = argparse.ArgumentParser()
    design.add_arguments(parser)  # the design command's own defaults for what trade does not ask
    argv = [robot, "--out", str(out)] + (["--layout", args.layout] if args.layout else [])
    argv += [f"--package-dir={d}" for d in dirs] + [f"--xacro-arg={a}" for a in xargs]
    design.run(parser.parse_args(argv))
    return str(out)


def add_arguments(p) -> None:
    p.add_argument("--knobs", default=None, help=f"comma-separated, from: {', '.join(KNOBS)} (default: all; with "
                   "--map or --robot those that run on any robot)")
    p.add_argument("--map", default=None, help="taxel map of a skin on any robot (`skinsafe design` writes one); "
                   "default: the UR5 sample skin")
    p.add_argument("--robot", default=None, help="a robot to design a skin on first (built-in name, franka for the "
                   "bundled Franka description, or a URDF/xacro/MJCF file), with --layout/--package-dir/--xacro-arg")
    p.add_argument("--layout", default=None, help="layout spec JSON for --robot (see `skinsafe design --help`)")
    p.add_argument("--package-dir", action="append", default=[], help="ROS package folder for --robot; repeatable")
    p.add_argument("--xacro-arg", action="append", default=[], metavar="NAME:=VALUE", help="xacro argument for --robot")
    p.add_argument("--quick", action="store_true", help="a reduced sweep (a few points per knob, smaller scenes)")
    p.add_argument("--address", default=None, help="an existing Ray cluster (host:6379, ray://host:10001, or auto "
                   "for one started with `ray start` here); default: start a local Ray")
    p.add_argument("--out", default="out/trade", help="folder for trade.png, trade.md, trade.json")
    p.add_argument("--json", action="store_true", help="print the rows as one JSON list")


def run(args) -> int:
    from skinsafe.core.app.cli import print_rows

    if args.map and args.robot:
        raise SystemExit("skinsafe trade: give --map or --robot, not both")
    where = args.map or (design_first(args) if args.robot else None)
    default = [k for k, kn in KNOBS.items() if kn.any_robot] if where else list(KNOBS)
    try:
        knobs = parse_knobs(args.knobs or default, where)
    except ValueError as e:
        raise SystemExit(f"skinsafe trade: --knobs: {e}")
    rows = run_sweep(knobs, quick=args.quick, address=args.address, out=args.out, where=where)
    print_rows(rows, args.json)
    for name in ("trade.png", "trade.md", "trade.json"):
        print(f"wrote {Path(args.out) / name}", file=sys.stderr)
    return 0
