"""One tracking run, the task every stage of `skinsafe experiment tracking` sends to Ray: a method
(vanilla, TDM or n-step TDM modulation) over all its episodes on one seed, its TDM re-trained after each.

Kept apart from the protocol and its report (`tracking`): a task's cache entry is valid while the sources
loaded where it ran are unchanged (`runner`), so a change to how results are summarised does not void
finished runs. `RunConfig` is every knob of a run (the scene's and the learning's), a frozen record that
travels in the task as a dict.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, fields

import mujoco
import numpy as np
import torch
from scipy.spatial import cKDTree

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

STATE = MOVING  # s = (pan, lift, elbow, wrist 1) angles, a = their nominal velocities
PROBE = 5  # ticks (0.1 s) before the desired path enters a ball: where `alignment_cos` is measured


@dataclass(frozen=True)
class RunConfig(TrackingTask):
    """Every knob of one run (the task's and the learning's); `quick()` is the test suite's run."""

    episodes: int = 10
    hidden: int = 64
    steps: int = 400  # most gradient steps per re-training (warm start, early stopping on a validation split)
    batch_size: int = 128
    lr: float = 3e-3
    labels: str = "binary"  # "binary": the paper's 0/1 taxel events; "distance": ramps from recorded contacts
    ramp: float = 0.08  # m, width of the distance labels' ramp
    total_weight: float = 1.0  # the TDM's extra loss on eq. 1's total danger (`FitConfig.total_weight`)
    label_stride: int = 3  # distance labels look at every k-th taxel
    max_train: int = 8000  # most states in a re-training set (a random subset of visited + noisy ones)
    augment: int = 0  # noisy copies of each visited state in the training set (0: the paper's, visited states only)
    state_noise: float = 0.05  # rad, their noise (also the n-step distillation's neighbourhood)
    horizon: int = 2
    gamma: float = 0.9
    samples: int = 8
    rollout_dt: float = 0.15  # s per step of the n-step rollouts
    action_range: float = 1.0  # rad/s, the uniform policy's box
    tangent_gain: float = 1.0  # modulation's tangential eigenvalue 1 + g f (1: the paper)
    distill_epochs: int = 40
    distill_points: int = 1500  # experience states (at most) the n-step targets are estimated at

    @staticmethod
    def quick() -> "RunConfig":
        return RunConfig(episodes=3, pitch=0.02, steps=200, distill_epochs=25, samples=8)

    @staticmethod
    def from_dict(d: dict) -> "RunConfig":
        """The record from its JSON form (lists back to tuples); keys it does not have are refused."""
        return RunConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


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
    it (`augment` 0, the paper's: visited states only, each labelled with what the skin felt there). Labels:
    `binary`, the paper's taxel events (a visited state's from its tick; a noisy copy's the skin's events at
    the noisy state, `TrackingScene.danger_at`: the simulator as an oracle at a pose the robot never visited,
    which a real robot does not have); `distance`, soft
    labels from the same events and the skin's own geometry: the world positions of every taxel that
    fired so far are the known obstacle points, and a state's label is `1 - d / ramp` (clipped at 0)
    for its closest taxel at distance d from them (0 for the others), so the total danger is a ramp of
    the distance to known contacts, for visited and noisy states alike.
    """

    def __init__(self, cfg: RunConfig, scene: TrackingScene, nstep: bool, seed: int):
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


def run_method(method: str, seed: int, config: dict, variant: str | None = None) -> dict:
    """All episodes of one method and seed (one Ray task); JSON-ready rows and the last episode's paths.
    `variant` names the result (an n-step grid point) instead of `method`."""
    torch.set_num_threads(1)
    single_thread_blas()
    cfg = RunConfig.from_dict(config)
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
