"""`skinsafe experiment tracking`: the command line of the tracking experiment (paper Fig. 11,
`core.experiments.tracking`): options to a frozen `TrackingConfig`, the run, and its files."""
from __future__ import annotations

import json
import os
import time
from dataclasses import replace
from pathlib import Path

from skinsafe.core.experiments import tracking, tracking_report
from skinsafe.core.experiments.runner import provenance
from skinsafe.core.experiments.stats import parse_seeds
from skinsafe.core.experiments.tracking import LABEL_SETS, METHODS, TrackingConfig
from skinsafe.core.skin.files import atomic_write

LABEL_CHOICES = {**{k: (k,) for k in LABEL_SETS}, "distance": ("soft",), "all": tuple(LABEL_SETS)}


def add_arguments(p) -> None:
    p.add_argument("--out", default="results/tracking", help="folder for tracking.json and the plots")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--full", action="store_true", help="the full run (default): the headline (binary labels of the visited "
                                                       "states) on seeds 10-19 and the replicate 20-29, the extensions on 10-19, 10 episodes")
    g.add_argument("--quick", action="store_true", help="reduced run (1 seed, 3 episodes, coarse skin, soft labels)")
    p.add_argument("--episodes", type=int, help="episodes per method and seed (default 10)")
    p.add_argument("--seeds", nargs="+", help="seeds, a range or a list: 10-19 (default), 11,12,13 or 11 12 13")
    p.add_argument("--methods", nargs="+", choices=METHODS, help="methods to run (default all)")
    p.add_argument("--labels", nargs="+", choices=sorted(LABEL_CHOICES),
                   help="label sets: binary (the paper's, the headline), binary-oracle and soft (= distance) the extensions, "
                        "all (the full run's default)")
    p.add_argument("--tangent-gain", type=float, help="tangential eigenvalue 1 + g f (default 1, the paper)")
    p.add_argument("--horizons", help="n-step grid: horizons T (a list, e.g. 1,2,3), each with every --rollout-dts")
    p.add_argument("--rollout-dts", help="n-step grid: rollout steps in s (a list, e.g. 0.05,0.15; default 0.15)")
    p.add_argument("--replicate-seeds", help="run the headline again on these seeds (a range or a list; full default "
                                             "20-29): verdicts per replicate and whether they agree")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s; 0: the tasks in this process, no Ray)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every task instead of reusing finished ones")
    p.add_argument("--no-progress", action="store_true")


def _numbers(text: str, flag: str, kind) -> list:
    """Positive numbers from "1,2,3"; a clear error on anything else."""
    try:
        out = [kind(x) for x in str(text).replace(" ", ",").split(",") if x]
    except ValueError:
        out = []
    if not out or min(out) <= 0:
        raise ValueError(f"{flag} is {text!r}; give positive numbers separated by commas, e.g. 1,2,3")
    return out


def config_from_args(args) -> TrackingConfig:
    """The experiment's record from the options; a bad option exits with a message naming the fix."""
    try:
        cfg = TrackingConfig.quick() if args.quick else TrackingConfig()
        run = cfg.run if args.episodes is None else replace(cfg.run, episodes=args.episodes)
        if args.tangent_gain is not None:
            run = replace(run, tangent_gain=args.tangent_gain)
        changes = {"run": run}
        if args.seeds:  # named seeds are one replicate unless --replicate-seeds names another
            changes.update(seeds=tuple(parse_seeds(args.seeds)), replicate_seeds=())
        if args.replicate_seeds:
            changes["replicate_seeds"] = tuple(parse_seeds(args.replicate_seeds))
        if args.methods:
            changes["methods"] = tuple(args.methods)
        if args.labels:
            changes["label_sets"] = tuple(dict.fromkeys(n for k in args.labels for n in LABEL_CHOICES[k]))
        if args.horizons or args.rollout_dts:
            Ts = _numbers(args.horizons, "--horizons", int) if args.horizons else [run.horizon]
            dts = _numbers(args.rollout_dts, "--rollout-dts", float) if args.rollout_dts else [run.rollout_dt]
            changes["nstep_grid"] = tuple((T, dt) for T in Ts for dt in dts)
        return replace(cfg, **changes)
    except ValueError as e:
        raise SystemExit(f"skinsafe experiment tracking: {e}") from None


def run(args) -> int:
    cfg = config_from_args(args)
    out = Path(args.out)
    t0, prov = time.perf_counter(), provenance()  # the tree the runs start from
    results = tracking.run_experiment(cfg, progress=not args.no_progress, cache=out / "tasks", address=args.address,
                                      workers=args.workers, fresh=args.fresh)
    doc = dict(tracking.document(results, cfg), provenance=prov, seconds=time.perf_counter() - t0)
    md = tracking_report.markdown(doc)
    atomic_write(out / "tracking.json", json.dumps(doc, indent=1))
    atomic_write(out / "tracking.md", md)
    paths = tracking_report.plot(doc, out)
    print(md)
    print(f"wrote {out / 'tracking.json'}, {out / 'tracking.md'}, " + ", ".join(str(p) for p in paths)
          + f" in {doc['seconds']:.0f} s ({doc['task_cpu_seconds']:.0f} CPU s in tasks)")
    return 0
