"""`skinsafe bench safety`: a correctness audit of the tactile defensiveness layer and the
safety stack, not a speed test (times are reported, but as a by-product).

Per built-in robot and contact count (1, 2, 3, 8), `--cases` random contact sets (taxels drawn
from the sample skin, half of the sets from one link so that opposite and identical normals
meet; forces 3-60 N, one set in ten 1e3-1e6 N; poses uniform in the joint ranges, one in five
with a joint at 0, the UR5's elbow and wrist singularities) are triggered at t = 0 and the
layer's command is integrated tick by tick (dt 2 ms) over the whole retraction (default alpha
0.05 m/N, T 0.5 s, epsilon 1). Row keys:

* `cases`, `feasible`: contact sets, and those whose every tick met all hard constraints (no-push,
  velocity and acceleration limits) without relaxing any;
* `into_contact_mm_worst`: the largest displacement of any contacted taxel toward its own
  contact (along +z at its trigger, from its trigger position), feasible cases, mm;
* `into_contact_mm_worst_all`: the same over all cases, infeasible ones included, while the
  contacts are held (every tick whose command was made with them in the pool), mm;
* `infeasible_cases`: cases with a tick flagged `infeasible` (no command within the limits met
  every no-push and viability row; the least-violating one was sent);
* `dominant_ratio_min`: achieved over eq. 10 speed of the highest-priority contact along its
  retraction axis, in feasible cases, over the ticks where eq. 10 asks for at least 5% of its
  peak speed and nothing binds the dominant task at that tick (no joint limit, no other
  contact's no-push constraint, no singularity damping: where a limit binds, saturation
  preserves priorities instead); `dominant_cases` says how many cases had such ticks;
* `vel_limit_violations`, `acc_limit_violations`: cases with any tick over a limit (all cases);
* `solver_failed`: cases with a tick whose QP solver gave up on the dominant level (flagged; the
  smallest command meeting every constraint was sent);
* `nonfinite_cases`: further cases run through the full stack (strategy filter + defensiveness
  + modulation with a small TDM), each with one fault injected at a random tick: a non-finite
  value (NaN, +Inf or -Inf) in the readings (at a touched or a random taxel), q, the clock, the
  planned command, the TDM output or the potential, or missing readings (`MISSING`: no readings
  at all, an empty dict, the force array cut short by one board's block, one board's block NaN);
* `missing_cases`: how many of those injected missing readings;
* `fail_open`: of all injection cases, those where the injected tick sent anything but the safe
  command (the brake from the last command) or, while retracting, a command that keeps every
  contacted taxel out of its contact - or where a later tick was non-finite;
* `ms_median`, `ms_worst`: the defensiveness tick over all ticks of the cases (`ms_p999`: the
  99.9th percentile, as the maximum on a shared machine is the scheduler's).

The default run (2,500 sets per robot and contact count) is fanned out with Ray in chunks of
`CHUNK` sets (`audit_task`, niced workers, the experiments' `run_tasks`: cached per chunk, a tqdm
bar); `--workers 0` runs in this process, `--from-cache` gives the rows of a stopped run's finished
chunks, `--out` writes the rows atomically.

With `--eq2` only, rows `estimator` = "eq2" instead: the bias of eq. 2's importance-sampling
estimate (`danger.marginal_danger`) against the exact integral, per sample count K, on a
proposal that puts little mass where the danger is (`bias_pct` over all estimates,
`bias_pct_reliable` over those marked reliable, `reliable_frac`, `ess_median`).
"""
from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import BUILTIN
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.limits import brake
from skinsafe.core.safety.retraction import RetractionParams, profile_rate
from skinsafe.core.skin.files import atomic_write

DT = 0.002
CONTACTS = (1, 2, 3, 8)
MISSING = ("readings_none", "readings_empty", "readings_short", "readings_board_nan")
INJECT = ("readings_touched", "readings_random", "q", "clock", "command", "tdm", "potential") + MISSING


def add_arguments(p) -> None:
    p.add_argument("--robots", default="ur5,panda", help="built-in robots (comma-separated)")
    p.add_argument("--contacts", default="1,2,3,8", help="contact counts (comma-separated)")
    p.add_argument("--cases", type=int, default=2500,
                   help="random contact sets per robot and contact count (2,500 x 4 = 10,000 per robot)")
    p.add_argument("--nonfinite", type=int, default=None,
                   help="non-finite injection cases per robot and contact count (default: cases / 10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eq2", action="store_true", help="instead: the bias of eq. 2's estimate vs sample count")
    p.add_argument("--workers", type=int, default=2, help="Ray workers (0: run in this process, no Ray)")
    p.add_argument("--cache", default="out/safety_audit_cache",
                   help="finished chunks are kept here; a rerun reuses them")
    p.add_argument("--from-cache", action="store_true",
                   help="no new work: rows from the chunks of this run already in --cache (a stopped run)")
    p.add_argument("--out", default=None, help="also write the rows to this JSON file (atomically)")


class Setup:
    """A robot, its sample skin and the layer's parameters."""

    def __init__(self, name: str, params: RetractionParams):
        self.robot = BUILTIN[name]()
        self.design = make_sample_design(name, robot=self.robot)
        self.kin = TaxelKinematics(self.robot.model, self.design)
        self.params = params
        m = self.robot.model
        rng = m.jnt_range[:m.nv].copy()
        free = ~m.jnt_limited[:m.nv].astype(bool)
        rng[free] = (-np.pi, np.pi)
        self.range = rng
        self.bodies = [np.flatnonzero(self.design.taxels.body == b) for b in range(len(self.design.bodies))]

    def layer(self) -> DefensivenessLayer:
        r = self.robot
        return DefensivenessLayer(self.kin, self.design.taxels.thresholds, r.vel_limits, r.acc_limits, self.params, DT)

    def draw(self, rng: np.random.Generator, contacts: int):
        """(q, taxels, forces) of one random contact set."""
        q = rng.uniform(self.range[:, 0], self.range[:, 1])
        if rng.random() < 0.2:
            j = rng.integers(len(q))
            q[j] = np.clip(0.0, *self.range[j])
        n = self.design.n_taxels
        pool = self.bodies[rng.integers(len(self.bodies))] if rng.random() < 0.5 else np.arange(n)
        idx = rng.choice(pool, min(contacts, len(pool)), replace=False)
        f = rng.uniform(3.0, 60.0, len(idx))
        if rng.random() < 0.1:
            f = 10 ** rng.uniform(3, 6, len(idx))
        return q, idx, f


def retraction_case(s: Setup, q, idx, f, times: list) -> dict:
    """Integrate one contact set; the audit's numbers for it."""
    L, p = s.layer(), s.params
    lim = L.limits
    force = np.zeros(s.design.n_taxels)
    force[idx] = f
    zero = np.zeros_like(force)
    _, p0, fr0 = s.kin.jacobians_of(idx, q)
    z0 = fr0[:, :, 2].copy()
    prev = np.zeros(len(q))
    out = {"into": 0.0, "into_all": 0.0, "ratio": np.inf, "feasible": True, "infeasible": False, "vel": False,
           "acc": False, "solver_failed": False}
    for k in range(int(np.ceil(p.T / DT)) + 3):
        t = k * DT
        t0 = time.perf_counter()
        qd = L.tick(t, q, {"force": force if k == 0 else zero}, None, DT)
        times.append(time.perf_counter() - t0)
        info = L.info
        v, a = lim.violations(qd, prev)
        out["vel"] |= v
        out["acc"] |= a
        out["feasible"] &= not (info.infeasible or info.recovery_dropped)
        out["infeasible"] |= info.infeasible
        out["solver_failed"] |= info.solver_failed
        held = L.active
        if L.active and not (info.limited or info.blocked or info.damped):
            st = L._state[0]
            D = min(st[2], 12 * p.max_distance)
            want = D * profile_rate((t - st[1]) / p.T) / p.T
            if want > 0.05 * D * 4 / 27 / p.T:
                J0 = s.kin.jacobians_of(L.pool[:1], q)[0][0]
                out["ratio"] = min(out["ratio"], float(-st[6:9] @ (J0[:3] @ qd)) / want)
        prev = qd
        q = q + qd * DT
        pos = s.kin.jacobians_of(idx, q)[1]
        into = float(np.max(np.einsum("ki,ki->k", pos - p0, z0)))
        out["into"] = max(out["into"], into)
        if held:
            out["into_all"] = max(out["into_all"], into)
    return out


def stack_for(s: Setup, seed: int):
    """The full stack (strategy filter + defensiveness + modulation) with a small random TDM."""
    import torch

    from skinsafe.core.safety.modulation import ModulationLayer
    from skinsafe.core.safety.potential import DangerPotential
    from skinsafe.core.safety.stack import SafetyStack, StrategyFilter
    from skinsafe.core.safety.tdm import TactileDangerModel

    torch.manual_seed(seed)
    nv = s.robot.model.nv
    tdm = TactileDangerModel(nv, nv, 64, (32, 32)).eval()
    return SafetyStack(s.robot.vel_limits, s.layer(), ModulationLayer(DangerPotential(tdm)), StrategyFilter(tdm), dt=DT)


def nonfinite_case(s: Setup, stack, rng: np.random.Generator, q, idx, f) -> tuple[bool, bool, bool, bool]:
    """One injection case: (fail_open, vel violated, acc violated, the injection was missing readings)."""
    stack.reset()
    d, lim = stack.defensiveness, stack.limits
    force = np.zeros(s.design.n_taxels)
    force[idx] = f
    zero = np.zeros_like(force)
    nv = len(q)
    plan = rng.uniform(-0.5, 0.5, nv) * lim.vel
    ticks = 40
    at, where = int(rng.integers(0, ticks)), INJECT[rng.integers(len(INJECT))]
    value = [np.nan, np.inf, -np.inf][rng.integers(3)]
    fail = vel = acc = False
    prev = np.zeros(nv)
    for k in range(ticks):
        t, qk, cmd = k * DT, q.copy(), plan.copy()
        r = {"force": (force if k == 0 else zero).copy()}
        saved = {}
        if k == at:
            if where in MISSING:
                r = _missing(s, r, where, rng)
            elif where.startswith("readings"):
                r["force"][idx[0] if where == "readings_touched" else rng.integers(len(force))] = value
            elif where == "q":
                qk[rng.integers(nv)] = value
            elif where == "clock":
                t = value
            elif where == "command":
                cmd[rng.integers(nv)] = value
            elif where == "tdm":
                saved["tdm"] = stack.strategy.fast.log_safety
                stack.strategy.fast.log_safety = lambda s_, a_: np.full(len(a_), value)
            else:
                saved["pot"] = stack.modulation._eval
                stack.modulation._eval = lambda s_, a_: (np.full(1, value), np.full((1, nv), value))
        out = stack.tick(t, qk, r, cmd, DT)
        if "tdm" in saved:
            stack.strategy.fast.log_safety = saved["tdm"]
        if "pot" in saved:
            stack.modulation._eval = saved["pot"]
        if not np.all(np.isfinite(out)):
            fail = True
            break
        v, a = lim.violations(out, prev)
        vel, acc = vel or v, acc or a
        if k == at:
            safe = np.array_equal(out, brake(prev, lim))
            retreat = d.active and np.all(d.A @ out >= -1e-6) and not np.array_equal(out, plan)
            fail |= not (safe or retreat)
        prev = out
        q = q + out * DT
    return fail, vel, acc, where in MISSING


def _missing(s: Setup, readings: dict, where: str, rng: np.random.Generator) -> dict | None:
    """Readings with a silent board: none at all, an empty dict, the force array without one
    board's block (cut short), or that block NaN (what the stream holds before a board's first frame)."""
    if where == "readings_none":
        return None
    if where == "readings_empty":
        return {}
    board = np.flatnonzero(s.design.taxels.board == rng.choice(np.unique(s.design.taxels.board)))
    force = readings["force"]
    if where == "readings_short":
        return {"force": np.delete(force, board)}
    force[board] = np.nan
    return {"force": force}


def eq2_rows(seed: int, reps: int = 300) -> list[dict]:
    """Eq. 2 on actions in [-3, 3]: target U uniform, proposal N(0.5, 0.7^2), danger
    sigmoid(4 (a - 1.5)) (mostly where the proposal rarely samples)."""
    from scipy.special import expit
    from scipy.stats import norm

    from skinsafe.core.safety.danger import marginal_danger

    grid = np.linspace(-3, 3, 200_001)
    exact = float(np.trapz(expit(4 * (grid - 1.5)), grid) / 6)
    rng = np.random.default_rng(seed)
    out = []
    for k in (10, 100, 1000, 10000):
        est = []
        for _ in range(reps):
            a = rng.normal(0.5, 0.7, k)
            log_u = np.where(np.abs(a) <= 3, -np.log(6.0), -np.inf)
            est.append(marginal_danger(expit(4 * (a - 1.5)), norm.logpdf(a, 0.5, 0.7), log_u))
        v = np.array([e.value for e in est])
        ok = np.array([e.reliable for e in est])
        out.append({"estimator": "eq2", "samples": k, "exact": round(exact, 5),
                    "bias_pct": round(float((v.mean() - exact) / exact * 100), 2),
                    "bias_pct_reliable": round(float((v[ok].mean() - exact) / exact * 100), 2) if ok.any() else None,
                    "reliable_frac": round(float(ok.mean()), 3),
                    "ess_median": round(float(np.median([e.ess for e in est])), 1)})
    return out


CHUNK = 250
"""Contact sets per audit task: a (robot, contact count) row is `cases / CHUNK` tasks fanned out
with Ray, each cached as it finishes (a restarted or shorter run reuses every finished chunk)."""
BINS = np.geomspace(1e-3, 1e4, 3501)
"""Tick-time histogram bin edges (ms, 0.46% wide): chunks merge exactly into the row's
median and 99.9th percentile to within one bin; the maximum is kept exactly."""


@functools.lru_cache(maxsize=4)
def _setup(name: str) -> Setup:
    """A worker's setup for one robot, warmed up (compiled code loaded) by one untimed case."""
    s = Setup(name, RetractionParams())
    retraction_case(s, *s.draw(np.random.default_rng(-1 % 2 ** 32), 8), [])
    return s


def audit_task(method: str, seed: int, robot: str, contacts: int, chunk: int, cases: int, nonfinite: int) -> dict:
    """One chunk of a row: `cases` contact sets and `nonfinite` injection cases on `robot` with
    `contacts` contacts, drawn from their own random stream (seed, robot, contacts, chunk);
    partial sums that `_merge` adds up. A module-level function: Ray runs it in its workers."""
    import torch

    torch.set_num_threads(1)
    s = _setup(robot)
    rng = np.random.default_rng([seed, sorted(BUILTIN).index(robot), contacts, chunk])
    times: list = []
    res = [retraction_case(s, *s.draw(rng, contacts), times) for _ in range(cases)]
    stack = stack_for(s, seed)
    bad = [nonfinite_case(s, stack, rng, *s.draw(rng, contacts)) for _ in range(nonfinite)]
    feas = [r for r in res if r["feasible"]]
    free = [r["ratio"] for r in feas if np.isfinite(r["ratio"])]
    ms = np.array(times) * 1e3
    hist = np.histogram(np.clip(ms, BINS[0], BINS[-1]), BINS)[0]
    return {"cases": len(res), "feasible": len(feas), "into": max((r["into"] for r in feas), default=0.0),
            "into_all": max((r["into_all"] for r in res), default=0.0),
            "infeasible": sum(r["infeasible"] for r in res), "missing": sum(b[3] for b in bad),
            "ratio": min(free, default=None), "dominant_cases": len(free),
            "vel": sum(r["vel"] for r in res) + sum(b[1] for b in bad),
            "acc": sum(r["acc"] for r in res) + sum(b[2] for b in bad),
            "nonfinite": len(bad), "fail_open": sum(b[0] for b in bad), "ms_max": float(ms.max(initial=0.0)),
            "solver_failed": sum(r["solver_failed"] for r in res),
            "hist": [[int(i), int(hist[i])] for i in np.flatnonzero(hist)]}


def niced_audit_task(**task) -> dict:
    """`audit_task` in a Ray worker that first lowers its own priority to niceness 19 (a long
    batch run on a shared machine; the driver and Ray's own processes keep theirs: Ray's start-up
    gives up after 30 s when starved)."""
    import os

    os.nice(max(19 - os.nice(0), 0))
    return audit_task(**task)


def _quantile(counts: np.ndarray, q: float) -> float:
    """The q-quantile of the binned tick times: the geometric centre of the bin holding it."""
    i = int(np.searchsorted(np.cumsum(counts), q * counts.sum()))
    return float(np.sqrt(BINS[i] * BINS[i + 1]))


def _merge(robot: str, contacts: int, parts: list[dict]) -> dict:
    """A row (module docstring) from its chunks."""
    counts = np.zeros(len(BINS) - 1, np.int64)
    for p in parts:
        for i, c in p["hist"]:
            counts[i] += c
    ratios = [p["ratio"] for p in parts if p["ratio"] is not None]
    return {"robot": robot, "contacts": contacts, "cases": sum(p["cases"] for p in parts),
            "feasible": sum(p["feasible"] for p in parts),
            "into_contact_mm_worst": round(max(p["into"] for p in parts) * 1e3, 4),
            "into_contact_mm_worst_all": round(max(p["into_all"] for p in parts) * 1e3, 4),
            "infeasible_cases": sum(p["infeasible"] for p in parts),
            "dominant_ratio_min": round(min(ratios), 4) if ratios else None,
            "dominant_cases": sum(p["dominant_cases"] for p in parts),
            "vel_limit_violations": sum(p["vel"] for p in parts), "acc_limit_violations": sum(p["acc"] for p in parts),
            "nonfinite_cases": sum(p["nonfinite"] for p in parts), "missing_cases": sum(p["missing"] for p in parts),
            "fail_open": sum(p["fail_open"] for p in parts),
            "solver_failed": sum(p["solver_failed"] for p in parts),
            "ms_median": round(_quantile(counts, 0.5), 4), "ms_worst": round(max(p["ms_max"] for p in parts), 3),
            "ms_p999": round(_quantile(counts, 0.999), 3)}


def tasks_for(robots: list[str], contacts: list[int], cases: int, n_bad: int, seed: int) -> list[dict]:
    """The audit's tasks, chunk-major (every row's first chunk first: a run stopped early has
    an even share of every row done)."""
    chunks = max(-(-cases // CHUNK), 1)
    out = []
    for chunk in range(chunks):
        n, m = min(CHUNK, cases - chunk * CHUNK), n_bad // chunks + (chunk < n_bad % chunks)
        for robot in robots:
            for c in contacts:
                out.append({"method": f"safety-{robot}-{c}c-{chunk}", "seed": seed, "robot": robot, "contacts": c,
                            "chunk": chunk, "cases": n, "nonfinite": m})
    return out


def rows(args) -> list[dict]:
    if args.eq2:
        return eq2_rows(args.seed)
    robots, contacts = args.robots.split(","), [int(c) for c in args.contacts.split(",")]
    n_bad = max(1, args.cases // 10) if args.nonfinite is None else args.nonfinite
    tasks = tasks_for(robots, contacts, args.cases, n_bad, args.seed)
    if args.from_cache:  # a stopped run: its finished chunks only
        from skinsafe.core.experiments.runner import cached

        results = [cached(Path(args.cache), t) for t in tasks]
        tasks, results = [t for t, r in zip(tasks, results) if r], [r for r in results if r]
    elif args.workers == 0:  # in this process, no Ray (small runs, tests)
        results = [audit_task(**t) for t in tqdm(tasks, desc="safety audit", leave=False)]
    else:
        from skinsafe.core.experiments.runner import run_tasks

        results = run_tasks(niced_audit_task, tasks, args.cache, workers=args.workers, desc="safety audit")
    parts = {(r, c): [x for t, x in zip(tasks, results) if (t["robot"], t["contacts"]) == (r, c)]
             for r in robots for c in contacts}
    out = [_merge(r, c, parts[r, c]) for r in robots for c in contacts if parts[r, c]]
    if args.out:
        atomic_write(args.out, json.dumps(out, indent=1) + "\n")
    return out
