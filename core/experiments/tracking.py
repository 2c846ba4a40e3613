"""`skinsafe experiment tracking`: the modulation layer on a UR5 tracking among balls (paper Fig. 11).

The task is `skinsafe.core.learn.tracking_env` (`skinsafe/Tracking-v0`): the UR5 with the sample skin
follows a pan sweep with the velocity controller `qd = qd_d + K clip(q_d - q)`; compliant balls sit on
the path (the exact path overlaps them for `path_contact_ticks` of the ticks, so only leaving the path
avoids contact). Three methods, each over `episodes` episodes and several seeds, one Ray task per
method x seed (cached in `--out`/tasks, reused by a restarted run):

- `vanilla`: the velocity controller as is;
- `tdm`: modulated by f_phi (eq. 4-7) of a TDM over all taxels, s = the four moving joints' angles,
  a = their nominal velocity, the one the layer queries the TDM with (wrist 2 and 3 are held and not
  modulated);
- `tdm2`: modulated by the distilled 2-step potential w_phi (eq. 8, uniform rollout policy); with
  `nstep_grid` (`--horizons`, `--rollout-dts`) also every other (horizon T, rollout step) pair, named
  `tdm<T>@<step>s`.

After every episode the method's TDM is re-trained (warm start, a budget of gradient steps with early
stopping on a validation split; AUC and calibration recorded per episode) on all its experience so far;
before any experience there is nothing to modulate with (episode 1 runs unmodulated). Labels (`Learner`):
the paper's binary taxel events (`binary`, the paper's setting; a noisy copy of a visited state gets the
skin's own events at the noisy state, `TrackingScene.danger_at`) and, as this project's extension, the
same events turned into distance-like soft targets (`soft`); the full run learns with both on the same
held-out seeds (10-19; the soft labels were designed on seeds 0-2), vanilla once per seed. Reported per
episode beside the contact ticks: contact onsets and, per ball, `alignment_cos`: cos(n, -grad d) of the
potential's normal n = df/ds against the true gradient of the skin's distance d to that ball, `PROBE`
ticks before the desired path enters it (1: the potential rises straight toward the ball).
`replicate_seeds` (the full run: 20-29) runs the whole grid again on other seeds: each verdict per
replicate and `verdict_agrees` (a verdict where the replicates differ is "not settled").

Writes `tracking.json`: per label set (`labels`: `binary`, `soft`) the per method/seed/episode rows
(contacts, contact onsets, tracking error, fit record), the summary (contact ticks per episode by
method), the per-seed table and the `claim` computed from them with 95% intervals over seeds; the
top-level `runs`, `summary` and `claim` are the paper's setting (binary) when it ran. `tracking.md` (the
tables), `contacts.png` (Fig. 11e: contacts per episode, mean and min-max band over seeds, one panel
per label set) and `trajectories.png` (Fig. 11b-d: end-effector paths with contact points, last
episode of the first seed).
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import mujoco
import numpy as np
import torch
from scipy.spatial import cKDTree

from skinsafe.core.experiments.runner import provenance, run_tasks
from skinsafe.core.experiments.stats import compare, mean_ci, parse_seeds, ratio_ci
from skinsafe.core.learn.tdm_training import FitConfig, TDMTrainer
from skinsafe.core.learn.tracking_env import MOVING, TrackingEnv, TrackingScene, TrackingTask
from skinsafe.core.realtime import single_thread_blas
from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.potential import (
    DangerPotential,
    EulerDynamics,
    NStepConfig,
    UniformPolicy,
    distill_nstep,
)
from skinsafe.core.safety.tdm import TactileDangerModel
from skinsafe.core.skin.files import atomic_write, write_png

METHODS = ("vanilla", "tdm", "tdm2")
LABEL_SETS = {"binary": "binary", "soft": "distance"}  # result name -> `TrackingConfig.labels`
RUN_COST = {"tdm2": 60.0, "tdm": 25.0, "vanilla": 1.0}  # CPU s of a 10-episode task (measured): the longest start first
HELD_OUT = tuple(range(10, 20))  # the full run's seeds: the soft labels and the scene were developed on 0-2
REPLICATE = tuple(range(20, 30))  # the full run's second replicate
STATE = MOVING  # s = (pan, lift, elbow, wrist 1) angles, a = their nominal velocities
PROBE = 5  # ticks (0.1 s) before the desired path enters a ball: where `alignment_cos` is measured


@dataclass
class TrackingConfig(TrackingTask):
    """Every knob of the experiment (the task's and the learning's); `quick()` is the test suite's run."""

    episodes: int = 10
    seeds: tuple = HELD_OUT
    methods: tuple = METHODS
    label_sets: tuple = ("binary", "soft")  # the experiment learns with each (`LABEL_SETS`); a task with one
    hidden: int = 64
    steps: int = 400  # most gradient steps per re-training (warm start, early stopping on a validation split)
    batch_size: int = 128
    lr: float = 3e-3
    labels: str = "distance"  # "binary": the paper's 0/1 taxel events; "distance": ramps from recorded contacts
    ramp: float = 0.08  # m, width of the distance labels' ramp
    total_weight: float = 1.0  # the TDM's extra loss on eq. 1's total danger (`FitConfig.total_weight`)
    label_stride: int = 3  # distance labels look at every k-th taxel
    max_train: int = 8000  # most states in a re-training set (a random subset of visited + noisy ones)
    augment: int = 3  # copies of each visited state with noise in the training set (labelled at the noisy state)
    state_noise: float = 0.05  # rad, their noise (also the n-step distillation's neighbourhood)
    horizon: int = 2
    gamma: float = 0.9
    samples: int = 8
    rollout_dt: float = 0.15  # s per step of the n-step rollouts
    action_range: float = 1.0  # rad/s, the uniform policy's box
    tangent_gain: float = 1.0  # modulation's tangential eigenvalue 1 + g f (1: the paper)
    distill_epochs: int = 40
    distill_points: int = 1500  # experience states (at most) the n-step targets are estimated at
    nstep_grid: tuple = ()  # extra (horizon, rollout step) pairs run beside tdm2 (`variant_name`)
    replicate_seeds: tuple = REPLICATE  # a second replicate of the grid on these seeds (empty: one replicate)

    @staticmethod
    def quick() -> "TrackingConfig":
        return TrackingConfig(episodes=3, seeds=(0,), pitch=0.02, steps=200, distill_epochs=25, samples=8,
                              label_sets=("soft",), replicate_seeds=())


@dataclass
class Episode:
    """One episode's log."""

    contacts: int  # control ticks with a tactile danger event
    onsets: int  # ticks where contact starts after a free tick
    tracking_error: float  # m, mean end-effector distance to the desired path
    states: np.ndarray = field(repr=False)  # (T, STATE) q of the moving joints
    actions: np.ndarray = field(repr=False)  # (T, STATE) their nominal velocity: the TDM's action (trained and queried)
    dangers: np.ndarray = field(repr=False)  # (T, N) bool events during the tick
    ee: np.ndarray = field(repr=False)  # (T, 3)
    ee_desired: np.ndarray = field(repr=False)  # (T, 3)
    contact_points: np.ndarray = field(repr=False)  # (K, 3) world positions of lit taxels (mean per tick)
    lit_points: np.ndarray = field(repr=False)  # (L, 3) world positions of every lit taxel
    alignment: list = field(default_factory=list)  # per ball: cos(n, -grad d) PROBE ticks before it (None: not measured)


def ball_entries(env: TrackingEnv) -> list[int]:
    """Per ball, the first tick at which this episode's desired path puts a taxel inside it (-1: never)."""
    sc, dt = env.scene, env.task.control_dt
    d = np.array([sc.ball_distances(sc.desired((k + 1) * dt, env.offset)[0]) for k in range(env.task.ticks)])
    return [int(np.argmax(col < 0)) if (col < 0).any() else -1 for col in d.T]


def alignment_cos(scene, q: np.ndarray, normal: np.ndarray, ball: int, h: float = 1e-4) -> float | None:
    """cos(n, -grad d) at joint angles q: n the potential's normal over the moving joints, d the skin's
    distance to `ball` (central differences); None where either vector vanishes."""
    g = np.zeros(STATE)
    for j in range(STATE):
        e = np.zeros(len(q))
        e[j] = h
        g[j] = (scene.ball_distances(q + e)[ball] - scene.ball_distances(q - e)[ball]) / (2 * h)
    n = np.asarray(normal, float).reshape(-1)[:STATE]
    den = float(np.linalg.norm(n) * np.linalg.norm(g))
    return float(-n @ g / den) if den > 1e-12 else None


def run_episode(env: TrackingEnv, layer: ModulationLayer | None, seed: int, probe: bool = False) -> Episode:
    """One tracking episode; `layer` None is the vanilla controller. `probe`: measure the layer's
    `alignment_cos` before each ball (`Episode.alignment`)."""
    obs, _ = env.reset(seed=seed)
    sc = env.scene
    probes = {}
    if probe and layer is not None:  # tick -> balls whose alignment is measured there
        for b, k in enumerate(ball_entries(env)):
            if k >= PROBE:
                probes.setdefault(k - PROBE, []).append(b)
    align = [None] * len(sc.balls)
    S, A, X, XD, P, L, D = [], [], [], [], [], [], []
    while True:
        q = obs[:6].astype(float)
        v_nom = env.nominal(obs)
        v = v_nom.copy()
        if layer is not None:  # the modulated state: the joints the task moves (wrist 2 and 3 are held)
            v[:STATE] = layer(q[:STATE], v_nom[:STATE])[0]
            for b in probes.get(len(S), ()):
                align[b] = alignment_cos(sc, q, layer.normal, b)
        obs, _, _, trunc, info = env.step(v)
        S.append(q[:STATE])
        A.append(v_nom[:STATE])
        X.append(info["ee"])
        XD.append(info["ee_desired"])
        D.append(info["taxel_danger"])
        if info["cost"]:
            pos, _ = sc.kin.poses(sc.data.qpos[sc.qadr])
            lit = pos[info["taxel_danger"]]
            P.append(lit.mean(0))
            L.append(lit)
        if trunc:
            break
    dangers = np.array(D)
    lit = dangers.any(1)
    onsets = int(lit[0]) + int(np.count_nonzero(lit[1:] & ~lit[:-1]))
    X, XD = np.array(X), np.array(XD)
    return Episode(contacts=int(lit.sum()), onsets=onsets, tracking_error=float(np.linalg.norm(X - XD, axis=1).mean()),
                   states=np.array(S), actions=np.array(A), dangers=dangers, ee=X, ee_desired=XD,
                   contact_points=np.array(P).reshape(-1, 3),
                   lit_points=np.concatenate(L) if L else np.zeros((0, 3)), alignment=align)


class Learner:
    """A method's TDM (and distilled n-step potential), re-trained on all experience after each episode.

    Training set (`training_set`): every visited (state, nominal velocity) and `augment` noisy copies of
    it. Labels: `binary`, the paper's taxel events (a visited state's from its tick; a noisy copy's the
    skin's events at the noisy state, `TrackingScene.danger_at`: a copy moved off the ball is safe); `distance`, soft
    labels from the same events and the skin's own geometry: the world positions of every taxel that
    fired so far are the known obstacle points, and a state's label is `1 - d / ramp` (clipped at 0)
    for its closest taxel at distance d from them (0 for the others), so the total danger is a ramp of
    the distance to known contacts, for visited and noisy states alike.
    """

    def __init__(self, cfg: TrackingConfig, scene: TrackingScene, nstep: bool, seed: int):
        self.cfg, self.scene, self.nstep, self.seed = cfg, scene, nstep, seed
        torch.manual_seed(seed)
        n_taxels = scene.design.n_taxels
        self.tdm = TactileDangerModel(STATE, STATE, n_taxels, (cfg.hidden, cfg.hidden))
        with torch.no_grad():  # prior: 1% total danger spread over the taxels, not 1% per taxel
            self.tdm.head.bias.fill_(float(np.log(0.01 / n_taxels)))
        self.trainer = TDMTrainer(self.tdm, FitConfig(steps=cfg.steps, batch_size=cfg.batch_size, lr=cfg.lr,
                                                      capacity=cfg.max_train, total_weight=cfg.total_weight), seed=seed)
        self.net = None
        self.S, self.A, self.D, self.points = [], [], [], []

    def labels(self, S: np.ndarray, D: np.ndarray) -> np.ndarray:
        """(len(S), N) training labels for states S (binary: D itself; distance: class doc)."""
        n = self.scene.design.n_taxels
        if self.cfg.labels == "binary":
            return D.astype(np.float32)
        y = np.zeros((len(S), n), np.float32)
        if not self.points:
            return y
        tree = cKDTree(np.unique(np.round(np.concatenate(self.points), 2), axis=0))  # 1 cm voxels
        kin, m = self.scene.kin, self.scene.kin.model
        idx = np.arange(0, n, self.cfg.label_stride)  # every k-th taxel: the pitch is finer than the ramp
        body, local = kin.body_id[idx], kin.local_pos[idx]
        q = self.scene.robot.home.copy()
        for k, s in enumerate(S):
            q[:STATE] = s
            kin.data.qpos[:] = q
            mujoco.mj_kinematics(m, kin.data)
            pos = kin.data.xpos[body] + np.einsum("nij,nj->ni", kin.data.xmat[body].reshape(-1, 3, 3), local)
            d, _ = tree.query(pos, distance_upper_bound=self.cfg.ramp)
            i = int(np.argmin(d))
            if np.isfinite(d[i]):
                y[k, idx[i]] = 1.0 - d[i] / self.cfg.ramp
        return y

    def training_set(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """States, actions and taxel events of the training set (class doc; a random subset of at most
        `max_train`) and each row's source: i < len(visited) the visited state i, else noisy copy
        i // len(visited) of visited state i % len(visited)."""
        cfg, k = self.cfg, self.cfg.augment
        S, A, D = np.concatenate(self.S), np.concatenate(self.A), np.concatenate(self.D)
        rng = np.random.default_rng(self.seed + len(self.S))
        S = np.concatenate([S] + [S + rng.normal(0, cfg.state_noise, S.shape) for _ in range(k)])
        keep = rng.permutation(len(S))[: cfg.max_train]
        visited = keep < len(D)
        events = np.zeros((len(keep), D.shape[1]), bool)
        events[visited] = D[keep[visited]]
        events[~visited] = self.scene.danger_at(S[keep[~visited]])
        return S[keep], np.tile(A, (k + 1, 1))[keep], events, keep

    def update(self, ep: Episode) -> tuple[ModulationLayer, dict]:
        cfg = self.cfg
        self.S.append(ep.states)
        self.A.append(ep.actions)
        self.D.append(ep.dangers)
        if len(ep.lit_points):
            self.points.append(ep.lit_points)
        S, A, D, _ = self.training_set()
        t = self.trainer
        t.n = t.i = 0  # the labels of old states change as contacts are found: rebuild the data set
        t.add(S, A, self.labels(S, D))
        rec = t.fit()
        pot = DangerPotential(self.tdm.eval())
        if not self.nstep:
            return ModulationLayer(pot, tangent_gain=cfg.tangent_gain), rec
        r = cfg.action_range
        pick = np.random.default_rng(self.seed).permutation(len(S))[: cfg.distill_points]
        self.net, info = distill_nstep(pot, S[pick], A[pick], EulerDynamics(cfg.rollout_dt),
                                       UniformPolicy(-r * np.ones(STATE), r * np.ones(STATE)),
                                       NStepConfig(cfg.horizon, cfg.gamma, cfg.samples), state_noise=cfg.state_noise,
                                       epochs=cfg.distill_epochs, seed=self.seed, net=self.net)
        return ModulationLayer(self.net.eval(), tangent_gain=cfg.tangent_gain), {**rec, **info}


def variant_name(horizon: int, rollout_dt: float) -> str:
    """The name of an n-step variant of the grid: `tdm<T>@<step>s`."""
    return f"tdm{int(horizon)}@{float(rollout_dt):g}s"


def run_method(method: str, seed: int, config: dict, variant: str | None = None) -> dict:
    """All episodes of one method and seed (one Ray task); JSON-ready rows and the last episode's paths.
    `variant` names the result (an n-step grid point) instead of `method`."""
    torch.set_num_threads(1)
    single_thread_blas()
    cfg = TrackingConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()})
    task = TrackingTask(**{f.name: getattr(cfg, f.name) for f in fields(TrackingTask)})
    scene = TrackingScene(task, seed)
    env = TrackingEnv(task, scene=scene)
    learner = None if method == "vanilla" else Learner(cfg, scene, method == "tdm2", seed)
    layer, rows, ep = None, [], None
    c0 = time.process_time()
    for e in range(cfg.episodes):
        t0 = time.perf_counter()
        ep = run_episode(env, layer, seed=1000 * seed + e, probe=True)
        row = {"episode": e, "contacts": ep.contacts, "onsets": ep.onsets, "tracking_error": ep.tracking_error,
               "alignment_cos": ep.alignment}
        if learner is not None:
            layer, fit = learner.update(ep)
            row["fit"] = {k: v for k, v in fit.items() if k in ("steps", "val_loss", "auc", "ece", "brier", "rmse")}
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
    return {"method": variant or method, "seed": seed, "rows": rows, "balls": scene.balls.tolist(), "cpu_seconds": time.process_time() - c0,
            "n_taxels": scene.design.n_taxels, "path_contact_ticks": scene.path_contact_ticks(),
            "last": {"ee": ep.ee.round(4).tolist(), "ee_desired": ep.ee_desired.round(4).tolist(),
                     "contact_points": ep.contact_points.round(4).tolist(), "contacts": ep.contacts}}


def run_experiment(cfg: TrackingConfig, progress: bool = True, cache: str | Path | None = None, address: str | None = None,
                   workers: int | None = None, fresh: bool = False) -> dict:
    """All methods x seeds x label sets (one Ray task each, cached in `cache`; vanilla, which learns
    nothing, once per seed); the merged results, per label set in `labels` (module doc)."""
    import tempfile

    config = json.loads(json.dumps(asdict(cfg)))
    unknown = [k for k in cfg.label_sets if k not in LABEL_SETS]
    if unknown or not cfg.label_sets:
        raise SystemExit(f"tracking: unknown label set(s) {unknown}; choose from {', '.join(LABEL_SETS)}")
    base = {k: v for k, v in config.items() if k not in ("seeds", "methods", "label_sets", "replicate_seeds")}
    seeds = list(dict.fromkeys([*cfg.seeds, *cfg.replicate_seeds]))
    grid = [(int(T), float(dt)) for T, dt in cfg.nstep_grid if (int(T), float(dt)) != (cfg.horizon, cfg.rollout_dt)]
    tasks = []  # a task: method x seed x labels (x n-step grid point)
    for name in cfg.label_sets:
        task_config = dict(base, labels=LABEL_SETS[name])
        tasks += [{"method": m, "seed": s, "config": task_config} for s in seeds for m in cfg.methods
                  if m != "vanilla" or name == cfg.label_sets[0]]
        if "tdm2" in cfg.methods:
            tasks += [{"method": "tdm2", "seed": s, "config": dict(task_config, horizon=T, rollout_dt=dt),
                       "variant": variant_name(T, dt)} for T, dt in grid for s in seeds]
    with tempfile.TemporaryDirectory() as tmp:
        out = run_tasks(run_method, tasks, cache or tmp, address=address, workers=workers, progress=progress,
                        desc="tracking runs", fresh=fresh, cost=lambda t: RUN_COST[t["method"]])
    results = {"config": config, "labels": {}, "balls": {}, "path_contact_ticks": {},
               "task_cpu_seconds": float(sum(r["cpu_seconds"] for r in out))}
    for name in cfg.label_sets:
        results["labels"][name] = {"runs": {}, "last": {}, "cpu_seconds": {}}
    for t, r in zip(tasks, out):
        names = list(cfg.label_sets) if r["method"] == "vanilla" else [n for n in cfg.label_sets if LABEL_SETS[n] == t["config"]["labels"]]
        for name in names:
            res = results["labels"][name]
            res["runs"].setdefault(r["method"], {})[str(r["seed"])] = r["rows"]
            res["cpu_seconds"].setdefault(r["method"], {})[str(r["seed"])] = r["cpu_seconds"]
            if r["seed"] == seeds[0]:  # the trajectories plotted (Fig. 11b-d): the first seed's last episode
                res["last"].setdefault(r["method"], {})[str(r["seed"])] = r["last"]
        results["balls"][str(r["seed"])] = r["balls"]
        results["path_contact_ticks"][str(r["seed"])] = r["path_contact_ticks"]
        results["n_taxels"] = r["n_taxels"]
    primary = results["labels"]["binary" if "binary" in cfg.label_sets else cfg.label_sets[0]]
    results.update(runs=primary["runs"], last=primary["last"], cpu_seconds=primary["cpu_seconds"])
    for res in results["labels"].values():
        del res["last"]  # the plotted set's is `last`
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


def claim_check(rows: list[dict], seeds: list[dict] | None = None) -> dict:
    """Fig. 11e's claim as the issue states it: the 2-step TDM's mean contacts over episodes 6-10 are at
    most 10% of vanilla's and below the TDM's. With per-seed rows (`per_seed`) each part is decided on a
    95% interval over the seeds (paired: a seed is one ball placement): the ratio 2-step / vanilla by a
    seeded bootstrap, the difference TDM - 2-step by Student's t; "holds" needs the whole ratio interval
    <= 10% and the whole difference interval > 0, "does not hold" an interval wholly on the wrong side.
    Without per-seed rows, the means decide."""
    by = {r["method"]: r["contacts_ep6_10"] for r in rows}
    if not {"vanilla", "tdm", "tdm2"} <= set(by):
        return {"holds": None, "verdict": "is not computed", "statement": "needs vanilla, tdm and tdm2"}
    x = {m: {p["seed"]: p["contacts_ep6_10"] for p in seeds or [] if p["method"] == m} for m in by}
    common = sorted(set(x["vanilla"]) & set(x["tdm"]) & set(x["tdm2"]))
    if len(common) >= 2:
        v, t, t2 = (np.array([x[m][s] for s in common]) for m in ("vanilla", "tdm", "tdm2"))
        ratio, rci = ratio_ci(t2, v)
        diff, dci = mean_ci(t - t2)
    else:
        ratio = by["tdm2"] / by["vanilla"] if by["vanilla"] > 0 else float("inf")
        diff = by["tdm"] - by["tdm2"]
        rci, dci = [ratio, ratio], [diff, diff]
    part_ratio = "holds" if rci[1] <= 0.1 else "does not hold" if rci[0] > 0.1 else "not resolved"
    part_diff = {"lower": "holds", "higher": "does not hold"}.get(compare(dci), "not resolved")
    holds = part_ratio == "holds" and part_diff == "holds"
    verdict = ("holds" if holds else "does not hold" if "does not hold" in (part_ratio, part_diff) else "is not resolved")
    n = max(len(common), 1)
    s = (f"Episodes 6-10, mean contact ticks per episode over {n} seed{'s' if n > 1 else ''}: vanilla {by['vanilla']:.1f}, "
         f"TDM {by['tdm']:.1f}, 2-step TDM {by['tdm2']:.1f}; 2-step / vanilla {100 * ratio:.1f}% [95% interval "
         f"{100 * rci[0]:.1f}, {100 * rci[1]:.1f}] ({part_ratio}: <= 10%), TDM - 2-step {diff:.1f} "
         f"[{dci[0]:.1f}, {dci[1]:.1f}] ({part_diff}: > 0). The paper's claim {verdict} here.")
    onsets = {r["method"]: r["onsets_ep6_10"] for r in rows if "onsets_ep6_10" in r}
    if {"vanilla", "tdm", "tdm2"} <= set(onsets):
        s += (f" Contact onsets per episode: vanilla {onsets['vanilla']:.1f}, TDM {onsets['tdm']:.1f}, "
              f"2-step TDM {onsets['tdm2']:.1f}.")
    return {"holds": bool(holds), "verdict": verdict, "tdm2_over_vanilla": ratio, "tdm2_over_vanilla_ci95": rci,
            "tdm_minus_tdm2": diff, "tdm_minus_tdm2_ci95": dci, "parts": {"ratio": part_ratio, "difference": part_diff},
            "seeds": common, "statement": s}


def markdown_table(table: list[dict], claim: dict, seeds: list[dict] | None = None, title: str = "") -> str:
    lines = ([f"### {title}", ""] if title else []) + [
        "| method | contact ticks, episode 1 | episodes 6-10: mean [95% interval] (std) over seeds | onsets, episodes "
        "6-10 [95% interval] | cos(n, -grad d) before the balls | last episode | all episodes | tracking error (mm) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in table:
        lo, hi = r["contacts_ep6_10_ci95_low"], r["contacts_ep6_10_ci95_high"]
        align = "—" if r["alignment_cos_ep6_10"] is None else f"{r['alignment_cos_ep6_10']:+.2f}"
        lines.append(f"| {r['method']} | {r['contacts_first']:.1f} | {r['contacts_ep6_10']:.1f} [{lo:.1f}, {hi:.1f}] "
                     f"({r['contacts_ep6_10_std']:.1f}) | {r['onsets_ep6_10']:.1f} [{r['onsets_ep6_10_ci95_low']:.1f}, "
                     f"{r['onsets_ep6_10_ci95_high']:.1f}] | {align} | {r['contacts_last']:.1f} | {r['contacts_mean']:.1f} | "
                     f"{r['tracking_error_mm']:.0f} |")
    text = "\n".join(lines) + "\n\n" + claim["statement"] + "\n"
    if seeds and len({p["seed"] for p in seeds}) > 1:
        ids = sorted({p["seed"] for p in seeds})
        text += ("\nPer seed, mean contact ticks over episodes 6-10:\n\n| method | " + " | ".join(f"seed {i}" for i in ids)
                 + " |\n| --- |" + " --- |" * len(ids) + "\n")
        for m in dict.fromkeys(p["method"] for p in seeds):
            by = {p["seed"]: p["contacts_ep6_10"] for p in seeds if p["method"] == m}
            text += f"| {m} | " + " | ".join(f"{by[i]:.1f}" if i in by else "-" for i in ids) + " |\n"
    return text


TITLES = {"binary": "The paper's setting: binary taxel labels", "soft": "Extension: soft distance labels"}


def plot(results: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"vanilla": "tab:red", "tdm": "tab:blue", "tdm2": "tab:green"}
    labels = {"vanilla": "no modulation", "tdm": "TDM modulation", "tdm2": "2-step TDM modulation"}
    sets = results.get("labels") or {"": {"runs": results["runs"]}}
    fig, axes = plt.subplots(1, len(sets), figsize=(6 * len(sets), 4), squeeze=False, sharey=True)
    for ax, (name, res) in zip(axes[0], sets.items()):
        for method, by_seed in res["runs"].items():
            c = np.array([[r["contacts"] for r in rows] for rows in by_seed.values()], float)
            ep = np.arange(1, c.shape[1] + 1)
            ax.plot(ep, c.mean(0), "o-", color=colors.get(method), label=labels.get(method, method))
            ax.fill_between(ep, c.min(0), c.max(0), color=colors.get(method), alpha=0.2)
        ax.set_xlabel("episode")
        ax.set_ylabel("contact ticks per episode")
        n = len(next(iter(res["runs"].values())))
        ax.set_title(f"{TITLES.get(name, 'UR5 tracking among balls')} ({n} seeds, min-max band)", fontsize=9)
        ax.legend()
    fig.tight_layout()
    paths = [out_dir / "contacts.png"]
    write_png(fig, paths[0])
    seed = next(iter(results["balls"]))
    methods = list(results["last"])
    fig = plt.figure(figsize=(5 * len(methods), 4.5))
    for i, method in enumerate(methods):
        ep = results["last"][method][seed]
        ax = fig.add_subplot(1, len(methods), i + 1, projection="3d")
        ax.plot(*np.array(ep["ee_desired"]).T, "k--", lw=1, label="desired")
        ax.plot(*np.array(ep["ee"]).T, color="tab:blue", lw=1.5, label="end effector")
        if len(ep["contact_points"]):
            ax.scatter(*np.array(ep["contact_points"]).T, color="tab:green", s=8, label="contact points")
        for c in results["balls"][seed]:
            ax.scatter(*c, color="tab:orange", s=120, alpha=0.6)
        ax.set_title(f"{labels.get(method, method)}: {ep['contacts']} contact ticks")
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out_dir / "trajectories.png")
    write_png(fig, paths[1])
    return paths


def add_arguments(p) -> None:
    p.add_argument("--out", default="results/tracking", help="folder for tracking.json and the plots")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--full", action="store_true", help="the full run (default): seeds 10-19 and the replicate 20-29 x 10 episodes, binary and soft labels")
    g.add_argument("--quick", action="store_true", help="reduced run (1 seed, 3 episodes, coarse skin, soft labels)")
    p.add_argument("--episodes", type=int, help="episodes per method and seed (default 10)")
    p.add_argument("--seeds", nargs="+", help="seeds, a range or a list: 10-19 (default), 11,12,13 or 11 12 13")
    p.add_argument("--methods", nargs="+", choices=METHODS, help="methods to run (default all)")
    p.add_argument("--labels", choices=("binary", "soft", "distance", "both"),
                   help="TDM labels: binary (the paper's), soft (= distance, this project's), both (the full run's default)")
    p.add_argument("--tangent-gain", type=float, help="tangential eigenvalue 1 + g f (default 1, the paper)")
    p.add_argument("--horizons", help="n-step grid: horizons T (a list, e.g. 1,2,3), each with every --rollout-dts")
    p.add_argument("--rollout-dts", help="n-step grid: rollout steps in s (a list, e.g. 0.05,0.15; default 0.15)")
    p.add_argument("--replicate-seeds", help="run the grid again on these seeds (a range or a list; full default "
                                             "20-29): verdicts per replicate and whether they agree")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s; 0: the tasks in this process, no Ray)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every task instead of reusing finished ones")
    p.add_argument("--no-progress", action="store_true")


def config_from_args(args) -> TrackingConfig:
    cfg = TrackingConfig.quick() if getattr(args, "quick", False) else TrackingConfig()
    if args.episodes is not None:
        if args.episodes < 1:
            raise SystemExit(f"--episodes is {args.episodes}; give at least 1")
        cfg.episodes = args.episodes
    if args.seeds:  # named seeds are one replicate unless --replicate-seeds names another
        cfg.seeds, cfg.replicate_seeds = tuple(parse_seeds(args.seeds)), ()
    if args.methods:
        cfg.methods = tuple(args.methods)
    labels = getattr(args, "labels", None)
    if labels:
        cfg.label_sets = ("binary", "soft") if labels == "both" else ("soft",) if labels == "distance" else (labels,)
    if getattr(args, "tangent_gain", None) is not None:
        cfg.tangent_gain = args.tangent_gain
    if getattr(args, "horizons", None) or getattr(args, "rollout_dts", None):
        Ts = _numbers(args.horizons, "--horizons", int) if args.horizons else [cfg.horizon]
        dts = _numbers(args.rollout_dts, "--rollout-dts", float) if args.rollout_dts else [cfg.rollout_dt]
        cfg.nstep_grid = tuple((T, dt) for T in Ts for dt in dts)
    if getattr(args, "replicate_seeds", None):
        cfg.replicate_seeds = tuple(parse_seeds(args.replicate_seeds))
        if set(cfg.replicate_seeds) & set(cfg.seeds):
            raise SystemExit(f"--replicate-seeds {args.replicate_seeds} overlaps --seeds; a replicate needs other seeds")
    return cfg


def _seed_range(seeds) -> str:
    return f"seeds {seeds[0]}-{seeds[-1]}" if len(seeds) > 1 else f"seed {seeds[0]}"


def _numbers(text: str, flag: str, kind) -> list:
    """Positive numbers from "1,2,3"; a clear exit on anything else."""
    try:
        out = [kind(x) for x in str(text).replace(" ", ",").split(",") if x]
    except ValueError:
        out = []
    if not out or min(out) <= 0:
        raise SystemExit(f"{flag} is {text!r}; give positive numbers separated by commas, e.g. 1,2,3")
    return out


def run(args) -> int:
    cfg = config_from_args(args)
    out = Path(args.out)
    t0 = time.perf_counter()
    results = run_experiment(cfg, progress=not args.no_progress, cache=out / "tasks", address=getattr(args, "address", None),
                             workers=getattr(args, "workers", None), fresh=getattr(args, "fresh", False))
    md = []
    groups = [cfg.seeds] + ([cfg.replicate_seeds] if cfg.replicate_seeds else [])
    for name, res in results["labels"].items():
        reps = []
        for k, seeds_k in enumerate(groups):
            sub = replicate(res, seeds_k)
            table, seeds = summary(sub), per_seed(sub)
            reps.append({"seeds": list(seeds_k), "summary": table, "per_seed": seeds, "claim": claim_check(table, seeds)})
            if k == 0:
                res.update(summary=table, contacts_per_episode=contacts_per_episode(sub), per_seed=seeds, claim=reps[0]["claim"])
        res["replicates"] = [{"seeds": r["seeds"], "verdict": r["claim"]["verdict"], "claim": r["claim"]} for r in reps]
        res["verdict_agrees"] = len({r["claim"]["verdict"] for r in reps}) == 1
        if not res["verdict_agrees"]:  # a verdict is stated only where every replicate gives it
            res["claim"] = dict(res["claim"], verdict="is not settled (the replicates differ)", holds=False)
        if len(reps) > 1:
            res["claim"]["statement"] += (" Replicates: " + "; ".join(f"{_seed_range(r['seeds'])} {r['claim']['verdict']}" for r in reps)
                                          + (" (the verdicts agree)." if res["verdict_agrees"] else
                                             " (the verdicts differ: the claim is not settled)."))
        md.append(markdown_table(res["summary"], res["claim"], res["per_seed"], TITLES[name]))
        md += [markdown_table(r["summary"], r["claim"], r["per_seed"], f"{TITLES[name]}, replicate {k + 1} ({_seed_range(r['seeds'])})") for k, r in enumerate(reps) if k > 0]
    primary = results["labels"]["binary" if "binary" in results["labels"] else cfg.label_sets[0]]
    doc = dict(results, summary=primary["summary"], per_seed=primary["per_seed"], claim=primary["claim"],
               replicates=primary["replicates"], verdict_agrees=primary["verdict_agrees"], provenance=provenance(),
               seconds=time.perf_counter() - t0)
    atomic_write(out / "tracking.json", json.dumps(doc, indent=1))
    atomic_write(out / "tracking.md", "\n".join(md))
    paths = plot(results, out)
    print("\n".join(md))
    print(f"wrote {out / 'tracking.json'}, {out / 'tracking.md'}, " + ", ".join(str(p) for p in paths)
          + f" in {doc['seconds']:.0f} s ({doc['task_cpu_seconds']:.0f} CPU s in tasks)")
    return 0
