"""`skinsafe experiment tracking`: the modulation layer on a UR5 tracking among balls (paper Fig. 11).

The task is `skinsafe.core.learn.tracking_env` (`skinsafe/Tracking-v0`): the UR5 with the sample skin
follows a pan sweep with the velocity controller `qd = qd_d + K clip(q_d - q)`; compliant balls sit on
the path (the exact path overlaps them for `path_contact_ticks` of the ticks, so only leaving the path
avoids contact). Three methods, each over `episodes` episodes and several seeds, one Ray task per
method x seed x label set (`tracking_runs.run_method`, cached in OUT/tasks, reused by a restarted run):

- `vanilla`: the velocity controller as is (once per seed: it learns nothing);
- `tdm`: modulated by f_phi (eq. 4-7) of a TDM over all taxels, s = the four moving joints' angles,
  a = their nominal velocity;
- `tdm2`: modulated by the distilled 2-step potential w_phi (eq. 8, uniform rollout policy); with
  `nstep_grid` also every other (horizon T, rollout step) pair, named `tdm<T>@<step>s`.

Label sets (`LABEL_SETS`): `binary`, the paper's and the headline: the taxel events the skin felt at the
visited states (`augment` 0); two extensions, each saying what it uses: `binary-oracle` adds 3 noisy copies
of every visited state labelled by MuJoCo at poses the robot never visited (an oracle a real robot lacks)
and `soft` distance-like labels from the skin's own contact points (3 noisy copies labelled by the same
distances). The headline runs on both replicates (seeds 10-19, then 20-29), the extensions on the first
(the budget).

The claim (Fig. 11e, `claim`), decided per replicate on paired seeds over episodes 6-10, four comparisons
with Holm's correction (`verdicts`): vanilla has more contacts than the TDM and than the 2-step TDM, the
2-step TDM has at most 10% of vanilla's (0.1 vanilla - 2-step > 0), and fewer than the TDM. Contacts are
counted as Fig. 11e counts them, in control ticks with contact (its "total number of contacts": Fig.
11b-d draw one contact point per such tick); the same claim on contact onsets is beside (`claim_onsets`).
Each label set's verdict is settled across its replicates (`verdicts.settle`).
"""
from __future__ import annotations

import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from skinsafe.core.experiments.runner import run_tasks
from skinsafe.core.experiments.stats import mean_ci, paired_p, ratio_ci
from skinsafe.core.experiments.tracking_runs import RunConfig, run_method
from skinsafe.core.experiments.verdicts import CORRECTION, Comparison, Test, decide, overall, settle

METHODS = ("vanilla", "tdm", "tdm2")
RUN_COST = {"tdm2": 40.0, "tdm": 20.0, "vanilla": 1.0}  # CPU s of a 10-episode task (measured): the longest start first
HELD_OUT = tuple(range(10, 20))  # the full run's seeds: the soft labels and the scene were developed on 0-2
REPLICATE = tuple(range(20, 30))  # the full run's second replicate
SHARE = 0.1  # "2-step ~ 0": at most this share of vanilla's contacts
COUNTS = {"contacts": "control ticks with contact (Fig. 11e's count: one contact point per such tick in Fig. 11b-d)",
          "onsets": "contact onsets (a tick in contact after a free one)"}


@dataclass(frozen=True)
class LabelSet:
    """How a method's TDM is labelled: `labels` and `augment` of its `RunConfig`; `headline` (the paper's
    setting, on every replicate) or an extension (the first replicate); `uses`: what its labels use."""

    labels: str
    augment: int
    headline: bool
    uses: str


LABEL_SETS = {
    "binary": LabelSet("binary", 0, True, "the paper's: the taxel events the skin felt at the visited states"),
    "binary-oracle": LabelSet("binary", 3, False, "extension: the paper's events plus 3 noisy copies of every visited "
                              "state labelled by MuJoCo at poses the robot never visited (the simulator as an oracle)"),
    "soft": LabelSet("distance", 3, False, "extension: distance-like labels from the skin's own contact points "
                     "(1 - d / 8 cm), the visited states and 3 noisy copies of each"),
}


@dataclass(frozen=True)
class TrackingConfig:
    """The experiment: the run's knobs (`run`), the seeds of each replicate, methods, label sets, n-step grid."""

    run: RunConfig = field(default_factory=RunConfig)
    seeds: tuple = HELD_OUT
    replicate_seeds: tuple = REPLICATE  # a second replicate of the headline on these seeds (empty: one replicate)
    methods: tuple = METHODS
    label_sets: tuple = tuple(LABEL_SETS)
    nstep_grid: tuple = ()  # extra (horizon, rollout step) pairs run beside tdm2 (`variant_name`)

    def __post_init__(self):
        unknown = [k for k in self.label_sets if k not in LABEL_SETS]
        if unknown or not self.label_sets:
            raise ValueError(f"unknown label set(s) {unknown}; choose from {', '.join(LABEL_SETS)}")
        if [m for m in self.methods if m not in METHODS] or not self.methods:
            raise ValueError(f"methods {list(self.methods)}: choose from {', '.join(METHODS)}")
        if not self.seeds or set(self.seeds) & set(self.replicate_seeds):
            raise ValueError(f"replicate seeds {list(self.replicate_seeds)} overlap seeds {list(self.seeds)}; a replicate "
                             "needs other seeds")
        if self.run.episodes < 1:
            raise ValueError(f"episodes is {self.run.episodes}; give at least 1")

    @staticmethod
    def quick() -> "TrackingConfig":
        return TrackingConfig(run=RunConfig.quick(), seeds=(0,), replicate_seeds=(), label_sets=("soft",))

    def replicates(self, name: str) -> list[tuple]:
        """The seeds of each replicate a label set runs on (an extension: the first only)."""
        both = [tuple(self.seeds)] + ([tuple(self.replicate_seeds)] if self.replicate_seeds else [])
        return both if LABEL_SETS[name].headline else both[:1]


def variant_name(horizon: int, rollout_dt: float) -> str:
    """The name of an n-step variant of the grid: `tdm<T>@<step>s`."""
    return f"tdm{int(horizon)}@{float(rollout_dt):g}s"


def run_experiment(cfg: TrackingConfig, progress: bool = True, cache: str | Path | None = None, address: str | None = None,
                   workers: int | None = None, fresh: bool = False) -> dict:
    """All methods x seeds x label sets (one Ray task each, cached in `cache`; vanilla, which learns
    nothing, once per seed); the raw runs, per label set in `labels`."""
    base = asdict(cfg.run)
    seeds_of = {name: [s for rep in cfg.replicates(name) for s in rep] for name in cfg.label_sets}
    every = list(dict.fromkeys(s for name in cfg.label_sets for s in seeds_of[name]))
    grid = [(int(T), float(dt)) for T, dt in cfg.nstep_grid if (int(T), float(dt)) != (cfg.run.horizon, cfg.run.rollout_dt)]
    first = LABEL_SETS[cfg.label_sets[0]]
    tasks = [({"method": "vanilla", "seed": s, "config": dict(base, labels=first.labels, augment=first.augment)}, list(cfg.label_sets))
             for s in every if "vanilla" in cfg.methods]
    for name in cfg.label_sets:
        ls = LABEL_SETS[name]
        conf = dict(base, labels=ls.labels, augment=ls.augment)
        tasks += [({"method": m, "seed": s, "config": conf}, [name]) for s in seeds_of[name] for m in cfg.methods if m != "vanilla"]
        if "tdm2" in cfg.methods:
            tasks += [({"method": "tdm2", "seed": s, "config": dict(conf, horizon=T, rollout_dt=dt), "variant": variant_name(T, dt)},
                       [name]) for T, dt in grid for s in seeds_of[name]]
    with tempfile.TemporaryDirectory() as tmp:
        out = run_tasks(run_method, [t for t, _ in tasks], cache or tmp, address=address, workers=workers, progress=progress,
                        desc="tracking runs", fresh=fresh, cost=lambda t: RUN_COST[t["method"]])
    results = {"labels": {name: {"runs": {}, "cpu_seconds": {}} for name in cfg.label_sets}, "balls": {},
               "path_contact_ticks": {}, "task_cpu_seconds": float(sum(r["cpu_seconds"] for r in out)), "last": {}}
    for (t, names), r in zip(tasks, out):
        for name in names:
            if r["seed"] in seeds_of[name]:
                res = results["labels"][name]
                res["runs"].setdefault(r["method"], {})[str(r["seed"])] = r["rows"]
                res["cpu_seconds"].setdefault(r["method"], {})[str(r["seed"])] = r["cpu_seconds"]
        if r["seed"] == every[0] and cfg.label_sets[0] in names:  # the trajectories plotted (Fig. 11b-d)
            results["last"].setdefault(r["method"], {})[str(r["seed"])] = r["last"]
        results["balls"][str(r["seed"])] = r["balls"]
        results["path_contact_ticks"][str(r["seed"])] = r["path_contact_ticks"]
        results["n_taxels"] = r["n_taxels"]
    return results


def _late(rows: list[dict], key: str = "contacts") -> float:
    """Mean of `key` (contact ticks) over episodes 6-10 (the second half when there are fewer than 10 episodes)."""
    c = np.array([r[key] for r in rows], float)
    return float((c[5:10] if len(c) > 5 else c[len(c) // 2:]).mean())


def _late_alignment(rows: list[dict]) -> float | None:
    """Mean alignment_cos over the balls probed in episodes 6-10 (the second half when fewer; None: none)."""
    late = rows[5:10] if len(rows) > 5 else rows[len(rows) // 2:]
    x = [c for r in late for c in r.get("alignment_cos") or [] if c is not None]
    return float(np.mean(x)) if x else None


def replicate(results: dict, seeds) -> dict:
    """The runs of `results` on `seeds` only (one replicate of the grid)."""
    keep = {str(s) for s in seeds}
    return {"runs": {m: {s: rows for s, rows in by.items() if s in keep} for m, by in results["runs"].items()}}


def summary(results: dict) -> list[dict]:
    """Per method (flat rows, for tables): contact ticks of the first and last episode, over all and over
    episodes 6-10 (mean, std and 95% interval over seeds), tracking error."""
    out = []
    for method, by_seed in results["runs"].items():
        c = np.array([[r["contacts"] for r in rows] for rows in by_seed.values()], float)  # (seeds, episodes)
        err = np.array([[r["tracking_error"] for r in rows] for rows in by_seed.values()])
        first_zero = [next((r["episode"] for r in rows if r["contacts"] == 0), None) for rows in by_seed.values()]
        late = [_late(rows) for rows in by_seed.values()]
        lo, hi = mean_ci(late)[1]
        onsets = mean_ci([_late(rows, "onsets") for rows in by_seed.values()])
        align = [a for a in (_late_alignment(rows) for rows in by_seed.values()) if a is not None]
        out.append({"method": method, "contacts_first": float(c[:, 0].mean()), "contacts_last": float(c[:, -1].mean()),
                    "contacts_mean": float(c.mean()), "contacts_ep6_10": float(np.mean(late)),
                    "contacts_ep6_10_std": float(np.std(late, ddof=1)) if len(late) > 1 else 0.0,
                    "contacts_ep6_10_ci95_low": lo, "contacts_ep6_10_ci95_high": hi,
                    "onsets_ep6_10": onsets[0], "onsets_ep6_10_ci95_low": onsets[1][0], "onsets_ep6_10_ci95_high": onsets[1][1],
                    "alignment_cos_ep6_10": float(np.mean(align)) if align else None,
                    "tracking_error_mm": float(err.mean() * 1e3), "first_zero_episode": first_zero, "seeds": len(late)})
    return out


def contacts_per_episode(results: dict) -> dict:
    """{method: contact ticks per episode, mean over seeds} (Fig. 11e)."""
    return {m: np.mean([[r["contacts"] for r in rows] for rows in by_seed.values()], axis=0).tolist()
            for m, by_seed in results["runs"].items()}


def per_seed(results: dict) -> list[dict]:
    """One row per method and seed: mean contact ticks and onsets over episodes 6-10, the last episode's
    contact ticks, the mean alignment_cos over episodes 6-10, tracking error."""
    return [{"method": m, "seed": int(seed), "contacts_ep6_10": _late(rows), "contacts_last": rows[-1]["contacts"],
             "onsets_ep6_10": _late(rows, "onsets"), "alignment_cos_ep6_10": _late_alignment(rows),
             "tracking_error_mm": float(np.mean([r["tracking_error"] for r in rows]) * 1e3)}
            for m, by_seed in results["runs"].items() for seed, rows in by_seed.items()]




@dataclass(frozen=True)
class TrackingClaim:
    """Fig. 11e's claim on one replicate: mean `count` per episode over episodes 6-10 by method, 2-step /
    vanilla with its bootstrap interval, the Holm-corrected comparisons and the verdict."""

    count: str
    means: dict
    tdm2_over_vanilla: float
    tdm2_over_vanilla_ci95: tuple[float, float]
    comparisons: tuple[Comparison, ...]
    verdict: str
    seeds: tuple[int, ...]


def claim(seeds: list[dict], count: str = "contacts") -> TrackingClaim | None:
    """The claim from per-seed rows (`per_seed`), paired over the seeds every method ran on (a seed is one
    ball placement); `count` "contacts" (ticks) or "onsets". None without vanilla, TDM and 2-step TDM."""
    key = f"{count}_ep6_10"
    x = {m: {p["seed"]: p[key] for p in seeds if p["method"] == m} for m in METHODS}
    common = sorted(set(x["vanilla"]) & set(x["tdm"]) & set(x["tdm2"]))
    if not common:
        return None
    v, t, t2 = (np.array([x[m][s] for s in common], float) for m in METHODS)
    ratio, rci = ratio_ci(t2, v)
    tests = []
    for name, d in (("vanilla above TDM", v - t), ("vanilla above 2-step TDM", v - t2),
                    (f"2-step TDM at most {SHARE:.0%} of vanilla", SHARE * v - t2), ("TDM above 2-step TDM", t - t2)):
        mu, ci = mean_ci(d)
        tests.append(Test(name, mu, tuple(ci), paired_p(d)))
    comparisons = decide(tests)
    return TrackingClaim(count, {m: float(np.mean(list(x[m].values()))) for m in METHODS}, ratio, tuple(rci),
                         comparisons, overall(comparisons), tuple(common))


def label_set_record(name: str, res: dict, cfg: TrackingConfig) -> dict:
    """One label set: what it uses, per replicate its summary, per-seed rows and claims (ticks and onsets),
    the verdict settled across its replicates, and contact ticks per episode over all its seeds (Fig. 11e)."""
    reps = []
    for seeds_k in cfg.replicates(name):
        sub = replicate(res, seeds_k)
        rows = per_seed(sub)
        ticks, onsets = claim(rows), claim(rows, "onsets")
        reps.append({"seeds": list(seeds_k), "summary": summary(sub), "per_seed": rows,
                     "claim": asdict(ticks) if ticks else None, "claim_onsets": asdict(onsets) if onsets else None})
    verdicts = [r["claim"]["verdict"] if r["claim"] else "not computed" for r in reps]
    onset_verdicts = [r["claim_onsets"]["verdict"] if r["claim_onsets"] else "not computed" for r in reps]
    ls = LABEL_SETS[name]
    return {"labels": ls.labels, "augment": ls.augment, "role": "headline" if ls.headline else "extension", "uses": ls.uses,
            "runs": res["runs"], "cpu_seconds": res["cpu_seconds"], "contacts_per_episode": contacts_per_episode(res),
            "replicates": reps, "settled": asdict(settle(verdicts)), "settled_onsets": asdict(settle(onset_verdicts))}


def document(results: dict, cfg: TrackingConfig) -> dict:
    """tracking.json: the run's knobs (`config`), the experiment (`experiment`), each label set's record
    (`labels`), the headline's name and runs (`headline`, `runs`: what the trajectories and views replay),
    how contacts are counted (`count`), the correction, and the scene per seed."""
    labels = {name: label_set_record(name, res, cfg) for name, res in results["labels"].items()}
    head = next(n for n in cfg.label_sets if LABEL_SETS[n].headline) if any(
        LABEL_SETS[n].headline for n in cfg.label_sets) else cfg.label_sets[0]
    first = LABEL_SETS[head]
    return {"config": dict(asdict(cfg.run), labels=first.labels, augment=first.augment),
            "experiment": {"seeds": list(cfg.seeds), "replicate_seeds": list(cfg.replicate_seeds), "methods": list(cfg.methods),
                           "label_sets": list(cfg.label_sets), "nstep_grid": [list(g) for g in cfg.nstep_grid]},
            "headline": head, "count": COUNTS, "correction": CORRECTION, "labels": labels, "runs": labels[head]["runs"],
            **{k: results[k] for k in ("last", "balls", "path_contact_ticks", "n_taxels", "task_cpu_seconds")}}
