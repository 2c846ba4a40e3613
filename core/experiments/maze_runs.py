"""One maze run, the task every stage of `skinsafe experiment maze` sends to Ray: a method trained on a seed.

Kept apart from the protocol and its report (`maze`): a task's cache entry is valid while the sources loaded
where it ran are unchanged (`runner`), so a change to how results are summarised does not void finished runs.
"""
from __future__ import annotations

import time

import numpy as np


def run_one(method: str, seed: int, episodes: int, max_steps: int, agent_kw: dict | None = None) -> dict:
    """Train one method with one seed; per-episode returns, contact events (costs), goals and lengths.
    `agent_kw` overrides the agent's keyword arguments (`make_agent`); a TDM `fit` is a FitConfig dict.
    Agents with an offline phase (RRL, SQRL) get their random transitions first; their contacts are
    `offline_contacts`, apart from the online `costs`."""
    import torch

    from skinsafe.core.learn.baselines import make_agent
    from skinsafe.core.learn.maze_env import MazeEnv, MazeFeatures, random_rollouts
    from skinsafe.core.learn.tdm_training import FitConfig

    torch.set_num_threads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    env = MazeEnv(max_steps=max_steps)
    kw = dict(agent_kw or {})
    if "fit" in kw:
        kw["fit"] = FitConfig(**kw["fit"])
    agent = make_agent(method, 4, env.action_space.n, env.n_taxels, MazeFeatures(env.walls), seed=seed, **kw)
    offline = {}
    if getattr(agent, "offline_transitions", 0) > 0:
        data = random_rollouts(env, agent.offline_transitions, np.random.default_rng(seed + 424242))
        agent.pretrain(**data)
        offline = {"offline_transitions": len(data["actions"]), "offline_contacts": int(data["costs"].sum())}
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
            **offline, "stats": stats, "tdm_fits": _thin(fits), "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0}


def _thin(fits: list[dict], keep: int = 30) -> list[dict]:
    """At most `keep` fit records, evenly spread (the result file stays small)."""
    if len(fits) <= keep:
        return fits
    return [fits[int(i)] for i in np.linspace(0, len(fits) - 1, keep)]
