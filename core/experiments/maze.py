"""`skinsafe experiment maze`: the strategy-layer experiment of the paper (Fig. 9) in the MuJoCo maze.

Nine methods (SAC, AC, each plain / -RP / -TDM, and the safe-RL baselines RRL, CPO, SQRL), one Ray task
per run (`maze_runs.run_one`, via `runner`: local Ray by default, a cluster by address, every finished run
cached in OUT/tasks and reused by a restarted run).

The full protocol (`MazeConfig()`; issue 51), the same for every method and every replicate:

1. defaults: trial 0 of every method is its published setting (`SPACES`, the source per method in
   `DEFAULTS_SOURCE`); a knob with no published value starts at the middle of its declared range, a
   mechanism of this project (the -TDM extras, the offline phase for the -TDM agents) off, so no method
   starts from values tuned on the experiment's seeds;
2. tuning (`tune`): one tuner (Optuna's TPE sampler, seeded) gives every method `trials` trials over its
   own search space (the -TDM mechanisms are switches there, like any knob) on the replicate's tuning
   seeds, under the evaluation's conditions (`conditions`: the same episodes and max steps, so the same
   CPO cost limit). One selection rule (`choose`, `CRITERION`);
3. evaluation: each chosen configuration on the held-out seeds (`eval_seeds`); the claims (`maze_claims`)
   decided on the replicate's runs with Holm's correction;
4. replicates: 2 and 3 again with the next tuning seeds and another sampler seed; each replicate is
   reported as itself (`replicates[i]`: its tuning, summary, claims) and each verdict settled across them
   (`verdicts.settle`);
5. ablation (`ablation`, off by default: the budget): each -TDM extra removed in turn from the first
   replicate's chosen configuration, each applicable one given to RRL and SQRL.
"""
from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from skinsafe.core.experiments.maze_claims import LAST, LEARNED_AT, WINDOW, claim_check, convergence
from skinsafe.core.experiments.maze_runs import run_one
from skinsafe.core.experiments.runner import run_tasks
from skinsafe.core.experiments.stats import diff_ci, mean_ci
from skinsafe.core.experiments.verdicts import CORRECTION, settle

METHODS = ("SAC", "SAC-RP", "SAC-TDM", "AC", "AC-RP", "AC-TDM", "RRL", "CPO", "SQRL")
TDM_METHODS = ("SAC-TDM", "AC-TDM")
ROUND = 4  # trials asked of every method's sampler at once (run together on Ray, then told in a fixed order)

# Each method's own search space: keyword -> (trial 0's value, the values tried): a list is a switch or
# a choice, ("log" | "float", low, high) a range. Trial 0 is the published default (`DEFAULTS_SOURCE`).
LR = ("log", 3e-4, 1e-2)
PRIOR = ("log", 1e-3, 1.0)
PENALTY = ("log", 1.0, 100.0)


def _tdm_space(lr: float) -> dict:
    """A -TDM agent: its base method's learning rate, the paper's filter (eq. 3 on the raw policy) with this
    project's mechanisms as switches, off at trial 0; the prior count (used only with shrinkage) at the
    geometric middle of its range."""
    return {"lr": (lr, LR), "prior_count": (float(np.sqrt(PRIOR[1] * PRIOR[2])), PRIOR), "raw_floor": (0.0, [0.0, 0.05]),
            "unfiltered_entropy": (False, [False, True]), "shrink": (False, [False, True]), "contact_steps": (0, [0, 100]),
            "offline_transitions": (0, [0, 4000])}


SPACES = {
    "SAC": {"lr": (3e-4, LR), "entropy_share": (0.3, ("float", 0.1, 0.5))},
    "SAC-RP": {"lr": (3e-4, LR), "cost_penalty": (50.0, PENALTY)},
    "SAC-TDM": _tdm_space(3e-4),
    "AC": {"lr": (7e-4, LR), "entropy_coef": (0.01, ("log", 0.005, 0.1))},
    "AC-RP": {"lr": (7e-4, LR), "cost_penalty": (50.0, PENALTY)},
    "AC-TDM": _tdm_space(7e-4),
    "RRL": {"lr": (3e-4, LR), "eps_risk": (0.15, ("float", 0.05, 0.5)), "offline_transitions": (4000, [4000, 0])},
    "CPO": {"lr": (1e-3, LR), "target_kl": (0.01, ("log", 0.005, 0.05))},  # the cost limit is the maze's (`cpo_budget`)
    "SQRL": {"lr": (3e-4, LR), "nu": (100.0, ("log", 1.0, 500.0)), "offline_transitions": (4000, [4000, 0])},
}
_SAC = "SAC-Discrete (Christodoulou 2019, Table 1): lr 3e-4"
_A2C = "OpenAI Baselines A2C (a2c.learn): lr 7e-4, ent_coef 0.01"
_RP = "reward penalty 50: recovery-rl's maze (scripts/maze.sh)"
_TDM = ("the paper's Bayes filter (eq. 3) on the raw policy, none of this project's mechanisms (floor, unfiltered "
        "entropy, visit-count shrinkage, contact refits, offline phase); prior count: the middle of its range (unused "
        "without shrinkage)")
DEFAULTS_SOURCE = {
    "SAC": f"{_SAC}; entropy share (this project's bound on the temperature, no published value): the middle of its range",
    "SAC-RP": f"{_SAC}; {_RP}",
    "SAC-TDM": f"{_SAC}; {_TDM}",
    "AC": _A2C,
    "AC-RP": f"{_A2C}; {_RP}",
    "AC-TDM": f"{_A2C}; {_TDM}",
    "RRL": "recovery-rl (arg_utils.py, scripts/maze.sh): lr 3e-4, eps_risk 0.15, gamma_safe 0.5, offline phase on",
    "CPO": "OmniSafe CPO (configs CPO.yaml): critic lr 1e-3, target_kl 0.01; cost limit: the maze's (68 wall-facing moves over the run)",
    "SQRL": "recovery-rl's SQRL (arg_utils.py, scripts/maze.sh): lr 3e-4, nu 100, eps 0.15, offline phase on",
}
# The -TDM extras, each removed in turn (ablation): what is removed and the keyword that removes it.
TDM_EXTRAS = (
    ("5% uniform floor", {"raw_floor": 0.0}),
    ("entropy on the unfiltered policy", {"unfiltered_entropy": False}),
    ("visit-count shrinkage", {"shrink": False}),
    ("contact refits (100 steps, the contact in every batch)", {"contact_steps": 0}),
)
# The extras that apply to RRL and SQRL, given to each in turn (their actors already learn the unfiltered policy).
BASELINE_EXTRAS = (
    ("5% uniform floor", {"floor": 0.05}),
    ("visit-count shrinkage", {"shrink": True}),
    ("contact refits (100 steps, the contact in every batch)", {"contact_steps": 100}),
)
BASELINES_GIVEN = ("RRL", "SQRL")
# Relative CPU cost of one run (measured), so every stage starts the longest first.
RUN_COST = {"SQRL": 5.0, "RRL": 5.0, "SAC-RP": 4.0, "SAC": 2.5, "CPO": 1.0, "SAC-TDM": 1.5, "AC-TDM": 1.5,
            "AC-RP": 0.4, "AC": 0.4}
CRITERION = (f"lowest mean total contacts among the trials whose mean goal rate over the last {LAST} episodes on "
             f"the tuning seeds is >= {LEARNED_AT}; none: the method never met the criterion and is evaluated at "
             "trial 0 (its published defaults)")


def cpo_budget(episodes: int) -> float:
    """CPO's cost limit per episode: the maze's 68 wall-facing moves (`maze_env.wall_moves`), each of which
    a learner that cannot see the walls must try once, spread over the run. A trained policy needs no
    contact at all; a larger budget licenses contacts no learner needs."""
    from skinsafe.core.learn.maze_env import LAYOUT, parse_layout, wall_moves

    return wall_moves(parse_layout(LAYOUT)[0]) / episodes


@dataclass(frozen=True)
class TdmOverrides:
    """Keyword overrides of every -TDM agent (None: the agent's own): periodic refit steps, the most danger the
    filter gives an untried move, the prior count."""

    refit_steps: int | None = None
    unseen_max: float | None = None
    prior_count: float | None = None

    def __post_init__(self):
        if self.refit_steps is not None and self.refit_steps < 1:
            raise ValueError(f"--tdm-refit-steps must be >= 1, got {self.refit_steps}")
        if self.unseen_max is not None and not 0 < self.unseen_max <= 1:
            raise ValueError(f"--tdm-unseen-max must lie in (0, 1], got {self.unseen_max}")
        if self.prior_count is not None and not self.prior_count > 0:
            raise ValueError(f"--tdm-prior-count must be > 0, got {self.prior_count}")

    def agent_kw(self) -> dict:
        kw = {}
        if self.refit_steps is not None:
            k = self.refit_steps
            kw["fit"] = {"steps": k, "min_steps": k, "batch_size": 64, "val_fraction": 0.1}
        if self.unseen_max is not None:
            kw["unseen_max"] = self.unseen_max
        if self.prior_count is not None:
            kw["prior_count"] = self.prior_count
        return kw


@dataclass(frozen=True)
class MazeConfig:
    """The experiment. `tune` False runs the defaults once (`DEMO`, `QUICK`); replicate r tunes on
    `tuning_seeds` shifted by r x their span with sampler seed r."""

    episodes: int = 60
    max_steps: int = 200
    eval_seeds: tuple = tuple(range(10, 18))
    tuning_seeds: tuple = (0,)
    replicates: int = 2
    trials: int = 4
    methods: tuple = METHODS
    tune: bool = True
    ablation: bool = False
    ablation_seeds: tuple = (10, 11)
    ablation_episodes: int = 30
    tdm: TdmOverrides = field(default_factory=TdmOverrides)

    def __post_init__(self):
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods:
            raise ValueError(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
        if min(self.episodes, self.max_steps, self.trials, self.replicates, self.ablation_episodes) < 1:
            raise ValueError("episodes, max steps, trials, replicates and ablation episodes must be >= 1, got "
                             f"{self.episodes}, {self.max_steps}, {self.trials}, {self.replicates}, {self.ablation_episodes}")
        overlap = sorted({s for r in range(self.replicates) for s in self.tuning_seeds_of(r)} & set(self.eval_seeds))
        if self.tune and overlap:
            raise ValueError(f"seeds {overlap} are both tuning and evaluation seeds (replicate r tunes on --tuning-seeds "
                             "shifted by r x their span); evaluate on held-out seeds (e.g. --tuning-seeds 0 --seeds 10-17)")
        if self.ablation and not set(self.ablation_seeds) <= set(self.eval_seeds):
            raise ValueError(f"--ablation-seeds {list(self.ablation_seeds)} must be evaluation seeds ({list(self.eval_seeds)}): "
                             "each variant is compared with its method's evaluation runs")

    def tuning_seeds_of(self, r: int) -> list[int]:
        span = self.tuning_seeds[-1] - self.tuning_seeds[0] + 1
        return [s + r * span for s in self.tuning_seeds]

    def conditions(self) -> dict:
        """What every tuning and evaluation run is trained under: episodes, max steps, CPO's cost limit per episode."""
        return {"episodes": self.episodes, "max_steps": self.max_steps, "cost_limit": cpo_budget(self.episodes)}


DEMO = MazeConfig(episodes=60, eval_seeds=(0, 1), replicates=1, tune=False)
QUICK = MazeConfig(episodes=2, max_steps=20, eval_seeds=(0,), replicates=1, tune=False)
PRESETS = {"full": MazeConfig(), "demo": DEMO, "quick": QUICK}


@dataclass(frozen=True)
class RunOptions:
    """Where and how the runs go: the output folder (its tasks/ caches every run), Ray, progress, re-runs."""

    out: Path
    address: str | None = None
    workers: int | None = None
    progress: bool = True
    fresh: bool = False


def run_row(r: dict) -> dict:
    """One run in a line: `total_contacts` (every contact the robot made: online, plus the offline phase's
    of RRL and SQRL), `online_contacts`, `offline_contacts`, goal rates (all episodes, last LAST)."""
    online, offline = float(sum(r["costs"])), float(r.get("offline_contacts", 0))
    return {"method": r["method"], "seed": r["seed"], "total_contacts": online + offline, "online_contacts": online,
            "offline_contacts": offline, "goal_rate": float(np.mean(r["goals"])),
            "goal_rate_last": float(np.mean(r["goals"][-LAST:])), "cpu_seconds": r.get("cpu_seconds")}


def _mean_std(x) -> tuple[float, float]:
    x = np.asarray(x, float)
    return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0


def summarise(runs: list[dict], methods: list[str]) -> dict:
    """One replicate's evaluation: per-method totals and goal rates (mean, std, 95% interval over seeds), the
    claim on total and on online contacts, Fig. 9c's convergence (records as dicts)."""
    per_seed = [run_row(r) for r in runs]
    rows = {}
    for m in methods:
        rs = [r for r in runs if r["method"] == m]
        per = [p for p in per_seed if p["method"] == m]
        row = {}
        for key in ("total_contacts", "online_contacts", "offline_contacts", "goal_rate", "goal_rate_last"):
            x = [p[key] for p in per]
            row[f"{key}_mean"], row[f"{key}_std"] = _mean_std(x)
            row[f"{key}_ci95"] = mean_ci(x)[1]
        rows[m] = {**row, "seeds_reaching": int(sum(p["goal_rate_last"] >= LEARNED_AT for p in per)),
                   "mean_steps": float(np.mean([np.mean(r["steps"]) for r in rs])), "seeds": len(rs)}
    total, online = claim_check(per_seed, methods), claim_check(per_seed, methods, "online_contacts")
    return {"methods": rows, "claim": asdict(total) if total else None,
            "claim_online": asdict(online) if online and any(p["offline_contacts"] for p in per_seed) else None,
            "convergence": asdict(convergence(runs, methods))}


# -- tuning -----------------------------------------------------------------------------------------
def choose(rows: list[dict], learned_at: float = LEARNED_AT) -> int | None:
    """Index of the chosen trial (`CRITERION`; ties: the earlier trial); None when no trial meets it."""
    ok = [i for i, r in enumerate(rows) if r["goal_rate_last_mean"] >= learned_at]
    return min(ok, key=lambda i: (rows[i]["total_contacts_mean"], i)) if ok else None


def objective(row: dict, learned_at: float = LEARNED_AT) -> float:
    """The number the sampler minimises, ordered as `choose` orders: a trial meeting the goal criterion
    scores its contacts, one missing it 10^6 per goal rate short of the criterion plus its contacts."""
    short = max(0.0, learned_at - row["goal_rate_last_mean"])
    return row["total_contacts_mean"] + (1e6 * (1 + short) if short > 0 else 0.0)


def agent_kw(method: str, config: dict, episodes: int, tdm: TdmOverrides) -> dict:
    """The agent's keyword arguments for a configuration: CPO gets the maze's cost limit for `episodes`,
    -TDM agents the command line's overrides."""
    kw = dict(config)
    if method == "CPO":
        kw.setdefault("cost_limit", cpo_budget(episodes))
    if method in TDM_METHODS:
        kw.update(tdm.agent_kw())
    return kw


def defaults(method: str) -> dict:
    """Trial 0 of a method: its published defaults (`SPACES`, `DEFAULTS_SOURCE`)."""
    return {k: default for k, (default, _) in SPACES[method].items()}


def _task(method, seed, episodes, max_steps, kw) -> dict:
    t = {"method": method, "seed": int(seed), "episodes": episodes, "max_steps": max_steps}
    if kw:
        t["agent_kw"] = kw
    return t


def _run(tasks, opts: RunOptions, desc: str, keep_ray: bool = False) -> list[dict]:
    return run_tasks(run_one, tasks, opts.out / "tasks", address=opts.address, workers=opts.workers,
                     progress=opts.progress, desc=desc, fresh=opts.fresh,
                     cost=lambda t: RUN_COST[t["method"]] * t["episodes"] * t["max_steps"], keep_ray=keep_ray)


def _stop_ray() -> None:
    """End a Ray this process started (without importing Ray when no stage needed it)."""
    if "ray" in sys.modules and sys.modules["ray"].is_initialized():
        sys.modules["ray"].shutdown()


def _distribution(values):
    import optuna.distributions as od

    if isinstance(values, list):
        return od.CategoricalDistribution(values)
    kind, lo, hi = values
    return od.FloatDistribution(lo, hi, log=kind == "log")


def tune(cfg: MazeConfig, seeds: list[int], sampler_seed: int, opts: RunOptions) -> tuple[dict, list[dict]]:
    """`cfg.trials` Optuna trials per method over its `SPACES` entry (trial 0 its published defaults; TPE,
    seeded, asked `ROUND` at a time per method, run together on Ray and told in a fixed order, so the trials
    are a function of the runs), each on `seeds` under the evaluation's conditions; per method every trial,
    the one `choose` picks (or none), and the runs."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    methods = list(cfg.methods)
    studies, dists, rows, runs = {}, {}, {m: [] for m in methods}, []
    for m in methods:
        sampler = optuna.samplers.TPESampler(seed=sampler_seed, n_startup_trials=max(1, cfg.trials // 2), constant_liar=True)
        studies[m] = optuna.create_study(direction="minimize", sampler=sampler)
        studies[m].enqueue_trial(defaults(m))
        dists[m] = {k: _distribution(values) for k, (_, values) in SPACES[m].items()}
    while len(rows[methods[0]]) < cfg.trials:
        n = min(ROUND, cfg.trials - len(rows[methods[0]]))
        asked = {m: [studies[m].ask(dists[m]) for _ in range(n)] for m in methods}
        tasks = [_task(m, s, cfg.episodes, cfg.max_steps, agent_kw(m, t.params, cfg.episodes, cfg.tdm))
                 for m in methods for t in asked[m] for s in seeds]
        done = _run(tasks, opts, f"maze tuning (seeds {seeds[0]}-{seeds[-1]}), {len(rows[methods[0]]) + n}/{cfg.trials} trials",
                    keep_ray=True)  # the next round and the evaluation reuse this Ray
        runs += done
        it = iter(done)
        for m in methods:
            for t in asked[m]:
                rs = [run_row(next(it)) for _ in seeds]
                row = {"trial": t.number, "config": t.params, "agent_kw": agent_kw(m, t.params, cfg.episodes, cfg.tdm),
                       "total_contacts_mean": float(np.mean([r["total_contacts"] for r in rs])),
                       "goal_rate_last_mean": float(np.mean([r["goal_rate_last"] for r in rs])),
                       "per_seed": [{k: r[k] for k in ("seed", "total_contacts", "goal_rate_last")} for r in rs]}
                studies[m].tell(t, objective(row))
                rows[m].append(row)
    record = {}
    for m in methods:
        i = choose(rows[m])
        record[m] = {"space": {k: values for k, (_, values) in SPACES[m].items()}, "trials": len(rows[m]),
                     "configs": rows[m], "met_criterion": i is not None, "chosen_index": i,
                     "chosen": rows[m][0 if i is None else i]["config"]}
    return record, runs


# -- the ablation -----------------------------------------------------------------------------------
def ablation_tasks(chosen: dict, cfg: MazeConfig) -> list[tuple[dict, dict]]:
    """(row head, task) for every ablation run: each -TDM extra removed from a -TDM method's chosen
    configuration, each applicable extra given to RRL and SQRL (variants identical to the chosen
    configuration are left out: they are its evaluation runs)."""
    out = []
    for m in cfg.methods:
        extras = TDM_EXTRAS if m in TDM_METHODS else BASELINE_EXTRAS if m in BASELINES_GIVEN else ()
        for what, delta in extras:
            kw = {**chosen[m], **delta}
            if kw == chosen[m]:
                continue
            head = {"method": m, "variant": f"{m} {'-' if m in TDM_METHODS else '+'} {what.split(' (')[0]}",
                    "removed": what if m in TDM_METHODS else None, "added": None if m in TDM_METHODS else what,
                    "agent_kw": kw}
            out += [(head, _task(m, s, cfg.ablation_episodes, cfg.max_steps, kw)) for s in cfg.ablation_seeds]
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
    rows = []
    for m in dict.fromkeys(h["method"] for h, _ in groups.values()):
        ref = [run_row(first_episodes(r, episodes)) for r in eval_runs if r["method"] == m and r["seed"] in seeds]
        base = [r["total_contacts"] for r in ref]
        mu, ci = mean_ci(base)
        rows.append({"method": m, "variant": f"{m} (chosen configuration)", "removed": None, "added": None,
                     "agent_kw": chosen[m], "total_contacts_mean": mu, "ci95": ci, "episodes": episodes,
                     "goal_rate_last_mean": float(np.mean([r["goal_rate_last"] for r in ref])), "seeds": len(ref),
                     "per_seed": [{k: r[k] for k in ("seed", "total_contacts", "goal_rate_last")} for r in ref]})
        for head, rs in (g for g in groups.values() if g[0]["method"] == m):
            x = [r["total_contacts"] for r in rs]
            mu, ci = mean_ci(x)
            d, dci = diff_ci(base, x)
            rows.append({**head, "total_contacts_mean": mu, "ci95": ci, "episodes": episodes,
                         "goal_rate_last_mean": float(np.mean([r["goal_rate_last"] for r in rs])),
                         "difference_to_chosen": d, "difference_ci95": dci, "seeds": len(rs),
                         "per_seed": [{k: r[k] for k in ("seed", "total_contacts", "goal_rate_last")} for r in rs]})
    return rows


# -- the protocol -----------------------------------------------------------------------------------
def run_protocol(cfg: MazeConfig, opts: RunOptions) -> dict:
    """Every stage (module doc); maze_results.json's document (`maze_report` writes it with its tables)."""
    t0 = time.perf_counter()
    methods = list(cfg.methods)
    reps = [{"tuning_seeds": cfg.tuning_seeds_of(r) if cfg.tune else [], "sampler_seed": r, "tuning": {}}
            for r in range(cfg.replicates)]
    stage = {"tuning": [], "evaluation": [], "ablation": []}
    try:
        if cfg.tune:
            for rep in reps:
                rep["tuning"], runs = tune(cfg, rep["tuning_seeds"], rep["sampler_seed"], opts)
                stage["tuning"] += runs
        for rep in reps:
            rep["chosen"] = {m: agent_kw(m, rep["tuning"][m]["chosen"] if rep["tuning"] else defaults(m), cfg.episodes, cfg.tdm)
                             for m in methods}
        eval_tasks = [_task(m, s, cfg.episodes, cfg.max_steps, rep["chosen"][m]) for rep in reps for s in cfg.eval_seeds
                      for m in methods]
        abl = ablation_tasks(reps[0]["chosen"], cfg) if cfg.ablation else []
        done = _run(eval_tasks + [t for _, t in abl], opts, "maze evaluation" + (" + ablation" if abl else ""))
    finally:
        _stop_ray()  # tuning keeps its Ray for the next stage; the end, a failure or an interrupt ends it
    per_rep = len(cfg.eval_seeds) * len(methods)
    for k, rep in enumerate(reps):
        rep["runs"] = done[k * per_rep:(k + 1) * per_rep]
        stage["evaluation"] += rep["runs"]
        rep["summary"], rep["per_seed"] = summarise(rep["runs"], methods), [run_row(r) for r in rep["runs"]]
    stage["ablation"] = done[len(eval_tasks):]
    sm = [r["summary"] for r in reps]
    claims = {"total": _settled([s["claim"] for s in sm]), "online": _settled([s["claim_online"] for s in sm]),
              "convergence": {c["name"]: asdict(settle([next(x["verdict"] for x in s["convergence"]["comparisons"]
                                                             if x["name"] == c["name"]) for s in sm]))
                              for c in sm[0]["convergence"]["comparisons"]}}
    return {"protocol": {"episodes": cfg.episodes, "max_steps": cfg.max_steps, "trials": cfg.trials if cfg.tune else 0,
                         "replicates": cfg.replicates, "tuning_seeds": [r["tuning_seeds"] for r in reps],
                         "sampler": "Optuna TPE, seeded by the replicate's index", "last": LAST, "learned_at": LEARNED_AT,
                         "window": WINDOW, "ablation": cfg.ablation},
            "selection_rule": CRITERION, "correction": CORRECTION,
            "defaults_source": {m: DEFAULTS_SOURCE[m] for m in methods},
            "tuning_conditions": cfg.conditions() if cfg.tune else None, "evaluation_conditions": cfg.conditions(),
            "eval_seeds": list(cfg.eval_seeds), "replicates": reps, "claims": claims,
            "ablation": ablation_rows(list(zip((h for h, _ in abl), stage["ablation"])), reps[0]["runs"], reps[0]["chosen"]) if abl else [],
            "stage_cpu_seconds": {k: float(sum(r.get("cpu_seconds", 0.0) for r in v)) for k, v in stage.items() if v},
            "wall_seconds": time.perf_counter() - t0}


def _settled(claims: list[dict | None]) -> dict | None:
    """A claim's verdict settled across the replicates (None where no replicate computed it)."""
    return asdict(settle([c["verdict"] for c in claims])) if all(claims) else None

