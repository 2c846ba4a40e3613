"""`skinsafe experiment maze`: the command line of the maze experiment (paper Fig. 9,
`core.experiments.maze`): options to a frozen `MazeConfig`, the protocol, and its files."""
from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

from skinsafe.core.experiments import maze_report
from skinsafe.core.experiments.maze import METHODS, PRESETS, MazeConfig, RunOptions, TdmOverrides, run_protocol
from skinsafe.core.experiments.runner import provenance
from skinsafe.core.experiments.stats import parse_seeds
from skinsafe.core.skin.files import atomic_write

FULL = PRESETS["full"]


def add_arguments(p) -> None:
    p.add_argument("--out", default="results/maze", help="folder for the plots, table and JSON (default: %(default)s)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--full", action="store_const", dest="preset", const="full",
                   help=f"the full protocol (default): {FULL.replicates} replicates of tuning ({FULL.trials} trials per method) and "
                        f"evaluation on held-out seeds, {FULL.episodes} episodes each")
    g.add_argument("--demo", action="store_const", dest="preset", const="demo", help="the demo's reduced run (defaults, no tuning)")
    g.add_argument("--quick", action="store_const", dest="preset", const="quick", help="smoke test (defaults, no tuning)")
    p.set_defaults(preset="full")
    p.add_argument("--seeds", help="evaluation seeds, a range or a list: 10-17 (full default) or 11,12,13 (--demo/--quick: 0-1 / 0)")
    p.add_argument("--tuning-seeds", help="tuning seeds of the first replicate (default 0; replicate r: shifted by r x their span)")
    p.add_argument("--trials", type=int, help=f"tuning trials per method, the same for every method (default {FULL.trials})")
    p.add_argument("--replicates", type=int, help=f"tuning + evaluation replicates (default {FULL.replicates})")
    p.add_argument("--episodes", type=int, help=f"episodes of every tuning and evaluation run (default {FULL.episodes})")
    p.add_argument("--max-steps", type=int, help=f"macro-actions per episode (default {FULL.max_steps})")
    p.add_argument("--ablation", action="store_true", help="also the ablation: each -TDM extra removed from replicate 1's "
                                                           "chosen configuration, each applicable one given to RRL and SQRL")
    p.add_argument("--ablation-seeds", help="evaluation seeds the ablation runs on (default 10-11)")
    p.add_argument("--ablation-episodes", type=int, help=f"episodes of every ablation run (default {FULL.ablation_episodes})")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of %(default)s")
    p.add_argument("--tdm-refit-steps", type=int, help="-TDM agents: gradient steps per periodic refit (default 25)")
    p.add_argument("--tdm-unseen-max", type=float, help="-TDM agents: most danger the filter gives an untried move (default 0.8)")
    p.add_argument("--tdm-prior-count", type=float, help="-TDM agents: tries of a move after which the filter trusts the TDM's danger half-way")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s; 0: the tasks in this process, no Ray)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every task instead of reusing finished ones")
    p.add_argument("--no-progress", action="store_true")


def config_from_args(args) -> MazeConfig:
    """The experiment's record from the options; a bad option exits with a message naming the fix."""
    try:
        cfg = PRESETS[args.preset]
        changes = {k: v for k, v in (("episodes", args.episodes), ("max_steps", args.max_steps), ("trials", args.trials),
                                     ("replicates", args.replicates), ("ablation_episodes", args.ablation_episodes)) if v is not None}
        if args.seeds:
            changes["eval_seeds"] = tuple(parse_seeds(args.seeds))
        if args.tuning_seeds:
            changes["tuning_seeds"] = tuple(parse_seeds(args.tuning_seeds))
        if args.ablation:
            changes["ablation"] = True
        if args.ablation_seeds:
            changes["ablation_seeds"] = tuple(parse_seeds(args.ablation_seeds))
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        changes.update(methods=methods, tdm=TdmOverrides(args.tdm_refit_steps, args.tdm_unseen_max, args.tdm_prior_count))
        return replace(cfg, **changes)
    except ValueError as e:
        raise SystemExit(f"skinsafe experiment maze: {e}") from None


def run(args) -> int:
    cfg = config_from_args(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    prov = provenance()  # the tree the runs start from
    doc = dict(run_protocol(cfg, RunOptions(out, args.address, args.workers, not args.no_progress, args.fresh)), provenance=prov)
    md = maze_report.markdown(doc)
    maze_report.plot_curves(doc, out / "maze_curves.png")
    atomic_write(out / "maze_contacts.md", md)
    atomic_write(out / "maze_results.json", json.dumps(doc, indent=1))
    print(md)
    print(f"wrote {out / 'maze_curves.png'}, {out / 'maze_contacts.md'}, {out / 'maze_results.json'} "
          f"({doc['wall_seconds']:.0f} s wall; CPU s in tasks: "
          + ", ".join(f"{k} {v:.0f}" for k, v in doc["stage_cpu_seconds"].items()) + ")")
    return 0
