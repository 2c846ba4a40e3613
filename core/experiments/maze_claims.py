"""The maze's claims as records (paper Fig. 9), decided on one replicate's evaluation runs.

- `claim_check` (Fig. 9b): the -TDM variants have the fewest contacts. Every (-TDM variant, other method)
  pair is one comparison of the family (Welch's test and interval of other - TDM per seed), Holm-corrected
  (`verdicts.decide`); the claim holds when every pair does. Beside it: the ordering of the means, the
  verdict among the methods that reach the goal (the same adjusted pairs), the goal-reaching runs of
  other methods that touched less than some -TDM run, and whether SAC, AC and their -TDM variants learned.
- `convergence` (Fig. 9c): per run the first episode from which the goal is reached in >= LEARNED_AT of
  WINDOW episodes; a run that never gets there is censored at its last episode, not given a number.
  Each -TDM variant against its plain method by the log-rank test, Holm-corrected over the pairs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skinsafe.core.experiments.stats import diff_ci, logrank_p, mean_ci, welch_p
from skinsafe.core.experiments.verdicts import Comparison, Test, decide, overall

LAST = 20  # episodes over which the final goal rate is measured
LEARNED_AT = 0.8  # a method "reaches the goal" when its mean goal rate over the last LAST episodes is at least this
WINDOW = 10  # episodes over which convergence (Fig. 9c) is judged
LEARNERS = ("SAC", "AC", "SAC-TDM", "AC-TDM")


@dataclass(frozen=True)
class MazeClaim:
    """Fig. 9b on one replicate, for one count (`measure`: total or online contacts per run)."""

    measure: str
    verdict: str
    means: dict
    ci95: dict
    comparisons: tuple[Comparison, ...]  # "<-TDM> vs <other>": difference = other - TDM (> 0: as claimed)
    holds_on_means: bool
    reaching: tuple[str, ...]  # methods whose mean goal rate over the last LAST episodes is >= LEARNED_AT
    verdict_among_reaching: str | None  # None: no -TDM variant or no other method reaches the goal
    seeds_beaten: tuple[dict, ...]
    learned: dict
    seeds: int


def claim_check(per_seed: list[dict], methods: list[str], key: str = "total_contacts") -> MazeClaim | None:
    """The claim from per-run rows (`maze.run_row`) of the methods given; None without a -TDM variant and
    another method."""
    tdm = [m for m in methods if m.endswith("-TDM")]
    other = [m for m in methods if not m.endswith("-TDM")]
    if not tdm or not other:
        return None
    x = {m: [p[key] for p in per_seed if p["method"] == m] for m in methods}
    goal = {m: float(np.mean([p["goal_rate_last"] for p in per_seed if p["method"] == m])) for m in methods}
    comparisons = decide([Test(f"{t} vs {o}", *_welch(x[t], x[o])) for t in tdm for o in other])
    mean = {m: float(np.mean(v)) for m, v in x.items()}
    reaching = tuple(m for m in methods if goal[m] >= LEARNED_AT)
    among = [c for c in comparisons if all(s in reaching for s in c.name.split(" vs "))]
    beaten = tuple({"method": p["method"], "seed": p["seed"], key: p[key],
                    "above": sorted(f"{q['method']} seed {q['seed']}" for q in per_seed if q["method"] in tdm and q[key] > p[key])}
                   for p in per_seed if p["method"] in other and p["goal_rate_last"] >= LEARNED_AT
                   and any(q["method"] in tdm and q[key] > p[key] for q in per_seed))
    return MazeClaim(key, overall(comparisons), mean, {m: tuple(mean_ci(v)[1]) for m, v in x.items()}, comparisons,
                     max(mean[t] for t in tdm) < min(mean[o] for o in other), reaching,
                     overall(among) if among else None, beaten, {m: goal[m] >= LEARNED_AT for m in LEARNERS if m in goal},
                     min(len(v) for v in x.values()))


def _welch(tdm, other) -> tuple[float, tuple[float, float], float]:
    d, ci = diff_ci(tdm, other)
    return d, tuple(ci), welch_p(tdm, other)


def converged_at(goals, window: int = WINDOW, learned_at: float = LEARNED_AT) -> int:
    """The first episode (1-based) from which the goal is reached in >= `learned_at` of `window` episodes;
    never: the number of episodes + 1 (censored: `convergence` never averages it)."""
    g = np.asarray(goals, float)
    hit = [e for e in range(len(g) - window + 1) if g[e:e + window].mean() >= learned_at]
    return hit[0] + 1 if hit else len(g) + 1


@dataclass(frozen=True)
class Convergence:
    """Fig. 9c on one replicate: per method how many runs converged, never did, and the median episode of
    those that did; per -TDM variant against its plain method the log-rank comparison (`difference` is
    the log-rank z statistic, > 0: the -TDM variant converges sooner)."""

    window: int
    episodes: int
    methods: dict
    comparisons: tuple[Comparison, ...]


def convergence(runs: list[dict], methods: list[str]) -> Convergence:
    episodes = max((len(r["goals"]) for r in runs), default=0)
    eps = {m: [converged_at(r["goals"]) for r in runs if r["method"] == m] for m in methods}
    rows = {m: {"converged": sum(e <= episodes for e in x), "never": sum(e > episodes for e in x),
                "median_episode_converged": float(np.median([e for e in x if e <= episodes])) if any(e <= episodes for e in x) else None}
            for m, x in eps.items() if x}
    tests = []
    for t in (m for m in methods if m.endswith("-TDM") and m[:-4] in rows and m in rows):
        z, p = logrank_p(eps[t], eps[t[:-4]], episodes)
        tests.append(Test(f"{t} vs {t[:-4]}", z, (z - 1.96, z + 1.96), p))
    return Convergence(WINDOW, episodes, rows, decide(tests))

