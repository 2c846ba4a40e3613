"""`skinsafe experiment tracking`: the modulation layer on a UR5 tracking among balls (paper Fig. 11).

The UR5 with the sample skin (whole arm: upper arm, forearm, wrists) follows a joint-space
sweep `q_d(t)` (pan -1 -> 1 -> -1 rad) with the velocity controller
`qd = qd_d + K clip(q_d - q)`; compliant solid balls (soft MuJoCo contact, so the unmodulated
arm pushes through them as in the paper's collision-detection simulation) sit under the arm's
sweep. Contacts come from the skin readout (`SkinReadout`) of the exported MuJoCo scene: a
control tick is a contact when any taxel's force exceeded its threshold during the tick. Three
methods, each over `episodes` episodes and several seeds (balls jittered per seed, trajectory
offset per episode):

- `vanilla`: the velocity controller as is;
- `tdm`: modulated by f_phi (eq. 4-7) of a TDM over all taxels, s = the four moving joints'
  angles, a = their nominal commanded velocity (wrist 2 and 3 are held and not modulated);
- `tdm2`: modulated by the distilled 2-step potential w_phi (eq. 8, uniform policy).

After every episode the method's TDM is re-trained (warm start, fixed step budget, states
augmented with small noise) on all its experience so far; before any experience there is
nothing to modulate with (episode 0 runs unmodulated). Writes `tracking.json` (per
method/seed/episode: contacts, contact onsets, tracking error), `contacts.png` (Fig. 11e:
contacts per episode, mean and min-max band over seeds) and `trajectories.png` (Fig. 11b-d:
end-effector paths with contact points, last episode of the first seed).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import mujoco
import numpy as np
import torch
from tqdm.auto import tqdm

from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.potential import (
    DangerPotential,
    EulerDynamics,
    NStepConfig,
    UniformPolicy,
    distill_nstep,
    single_thread_blas,
)
from skinsafe.core.safety.tdm import TactileDangerModel, train_tdm
from skinsafe.core.skin.files import atomic_write

METHODS = ("vanilla", "tdm", "tdm2")
STATE = 4  # s = (pan, lift, elbow, wrist 1) angles, a = their commanded velocities


@dataclass
class TrackingConfig:
    """Every knob of the experiment; `quick()` is the reduced run of the test suite."""

    episodes: int = 10
    seeds: tuple = (0, 1, 2)
    methods: tuple = METHODS
    duration: float = 6.0  # s per episode (one sweep out and back)
    control_dt: float = 0.02  # s per control tick
    gain: float = 3.0  # 1/s, joint-space position feedback
    max_error: float = 0.15  # rad, the feedback error is saturated here (no wind-up into an obstacle)
    lead: float = 0.2  # rad, most the servo target may run ahead of the joint (anti wind-up)
    pitch: float = 0.01  # sample skin pitch (m)
    n_balls: int = 3
    ball_radius: float = 0.06
    penetration: float = 0.02  # m the balls reach into the nominal sweep of the arm
    ball_solimp: tuple = (0.0, 0.1, 0.05, 0.5, 2.0)  # compliant balls (MuJoCo solimp): the arm pushes through
    jitter: float = 0.01  # m, ball position noise per seed
    traj_noise: float = 0.01  # rad, trajectory offset noise per episode
    hidden: int = 64
    steps: int = 400  # gradient steps per re-training (warm start), spread over all experience
    batch_size: int = 64
    augment: int = 3  # noisy copies of each state in the TDM's training set
    state_noise: float = 0.03  # rad, their noise (also the n-step distillation's neighbourhood)
    lr: float = 3e-3
    horizon: int = 2
    gamma: float = 0.9
    samples: int = 8
    rollout_dt: float = 0.15  # s per step of the n-step rollouts
    action_range: float = 1.0  # rad/s, the uniform policy's box
    tangent_gain: float = 1.0  # modulation's tangential eigenvalue 1 + g f (1: the paper)
    distill_epochs: int = 40
    distill_points: int = 1500  # experience states (at most) the n-step targets are estimated at

    @staticmethod
    def quick() -> "TrackingConfig":
        return TrackingConfig(episodes=3, seeds=(0,), pitch=0.02, steps=200, distill_epochs=25, samples=8)


@dataclass
class Episode:
    """One episode's log."""

    contacts: int  # control ticks with a tactile danger event
    onsets: int  # ticks where contact starts after a free tick
    tracking_error: float  # m, mean end-effector distance to the desired path
    states: np.ndarray = field(repr=False)  # (T, STATE) q of the moving joints
    actions: np.ndarray = field(repr=False)  # (T, STATE) their nominal commanded velocity (the TDM's action)
    dangers: np.ndarray = field(repr=False)  # (T, N) bool events during the tick
    ee: np.ndarray = field(repr=False)  # (T, 3)
    ee_desired: np.ndarray = field(repr=False)  # (T, 3)
    contact_points: np.ndarray = field(repr=False)  # (K, 3) world positions of lit taxels


class TrackingScene:
    """The UR5 + sample skin + balls as a MuJoCo model, the desired trajectory and the readout."""

    def __init__(self, cfg: TrackingConfig, seed: int):
        from skinsafe.core.design.sample import make_sample_design
        from skinsafe.core.robot.kinematics import TaxelKinematics
        from skinsafe.core.robot.models import build_ur5
        from skinsafe.core.sim.readout import SkinReadout
        from skinsafe.core.sim.scene import Obstacle, build_scene

        self.cfg = cfg
        self.robot = build_ur5()
        self.design = make_sample_design("ur5", pitch=cfg.pitch, robot=self.robot)
        self.kin = TaxelKinematics(self.robot.model, self.design)
        centers = self._ball_centers(np.random.default_rng(1000 + seed))
        self.balls = centers
        obstacles = [Obstacle(f"ball{k}", "sphere", (cfg.ball_radius,), pos=tuple(c), rgba=(0.9, 0.5, 0.1, 1))
                     for k, c in enumerate(centers)]
        spec = build_scene(self.design, self.robot, obstacles)
        for k in range(len(centers)):  # compliant balls: the arm can push through, the skin feels it
            spec.geom(f"ball{k}").solimp = list(cfg.ball_solimp)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.readout = SkinReadout(self.model, self.design)
        self.thresholds = self.design.taxels.thresholds["force"]
        self.substeps = max(1, int(round(cfg.control_dt / self.model.opt.timestep)))
        self.flange = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "flange")
        self.kin_flange = mujoco.mj_name2id(self.robot.model, mujoco.mjtObj.mjOBJ_SITE, "flange")
        self.qadr = np.array([self.model.jnt_qposadr[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, j)]
                              for j in ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                                        "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")])

    def desired(self, t: float, offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """q_d(t) and its rate: a pan sweep from -1 rad to 1 and back."""
        w = 2 * np.pi / self.cfg.duration
        amp = np.array([-1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        freq = np.array([w, 2 * w, 2 * w, 2 * w, 0, 0])
        shift = np.array([np.pi / 2, 0, 0, 0, 0, 0])  # pan = -cos(w t)
        q = self.robot.home + amp * np.sin(freq * t + shift) + (0 if offset is None else offset)
        return q, amp * freq * np.cos(freq * t + shift)

    def _ball_centers(self, rng: np.random.Generator) -> np.ndarray:
        """Balls under the arm's sweep: below a forearm/wrist taxel at evenly spread times."""
        cfg, t = self.cfg, self.design.taxels
        names = self.design.bodies
        on = np.isin(t.body, [names.index(b) for b in ("forearm_link", "wrist_1_link") if b in names])
        out = []
        for k in range(cfg.n_balls):
            tk = cfg.duration * (0.1 + 0.3 * (k + 0.5) / cfg.n_balls)  # spread over the outward sweep
            pos, _ = self.kin.poses(self.desired(tk)[0])
            p = pos[on]
            lo = p[np.argsort(p[:, 2])[: max(1, len(p) // 20)]].mean(0)  # the underside
            c = lo - np.array([0, 0, cfg.ball_radius - cfg.penetration])
            out.append(c + rng.normal(0, cfg.jitter, 3))
        return np.array(out)

    def reset(self, q0: np.ndarray) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.qadr] = q0
        self.data.ctrl[:] = q0
        mujoco.mj_forward(self.model, self.data)


def run_episode(scene: TrackingScene, layer: ModulationLayer | None, rng: np.random.Generator) -> Episode:
    """One tracking episode; `layer` None is the vanilla controller."""
    cfg, m, d = scene.cfg, scene.model, scene.data
    offset = rng.normal(0, cfg.traj_noise, 6) * np.array([1, 1, 1, 1, 0, 0])
    q0, _ = scene.desired(0.0, offset)
    scene.reset(q0)
    ticks = int(round(cfg.duration / cfg.control_dt))
    vmax = scene.robot.vel_limits
    S, A, X, XD, P = [], [], [], [], []
    dangers = np.zeros((ticks, scene.design.n_taxels), bool)
    q_cmd = q0.copy()
    for k in range(ticks):
        t = k * cfg.control_dt
        q = d.qpos[scene.qadr].copy()
        qd_, vd_ = scene.desired(t + cfg.control_dt, offset)
        v_nom = vd_ + cfg.gain * np.clip(qd_ - q, -cfg.max_error, cfg.max_error)
        v = v_nom.copy()
        if layer is not None:  # the modulated state: the joints the task moves (wrist 2 and 3 are held)
            v[:STATE] = layer(q[:STATE], v_nom[:STATE])[0]
        v = v * min(1.0, float(np.min(vmax / np.maximum(np.abs(v), 1e-12))))
        # integrate the command; the servo target never runs more than `lead` ahead (anti wind-up)
        q_cmd = np.clip(q_cmd + v * cfg.control_dt, q - cfg.lead, q + cfg.lead)
        d.ctrl[:] = q_cmd
        peak = np.zeros(scene.design.n_taxels)
        for _ in range(scene.substeps):
            mujoco.mj_step(m, d)
            peak = np.maximum(peak, scene.readout.read(d))
        dangers[k] = peak > scene.thresholds
        S.append(q[:STATE])
        A.append(v_nom[:STATE])
        X.append(d.site_xpos[scene.flange].copy())
        scene.kin.update(scene.desired(t + cfg.control_dt, offset)[0])
        XD.append(scene.kin.data.site_xpos[scene.kin_flange].copy())
        if dangers[k].any():
            pos, _ = scene.kin.poses(d.qpos[scene.qadr])
            P.append(pos[dangers[k]].mean(0))
    lit = dangers.any(1)
    onsets = int(lit[0]) + int(np.count_nonzero(lit[1:] & ~lit[:-1]))
    X, XD = np.array(X), np.array(XD)
    return Episode(contacts=int(lit.sum()), onsets=onsets, tracking_error=float(np.linalg.norm(X - XD, axis=1).mean()),
                   states=np.array(S), actions=np.array(A), dangers=dangers, ee=X, ee_desired=XD,
                   contact_points=np.array(P).reshape(-1, 3))


class Learner:
    """A method's TDM (and distilled n-step potential), re-trained on all experience after each episode."""

    def __init__(self, cfg: TrackingConfig, n_taxels: int, nstep: bool, seed: int):
        self.cfg, self.nstep, self.seed = cfg, nstep, seed
        torch.manual_seed(seed)
        self.tdm = TactileDangerModel(STATE, STATE, n_taxels, (cfg.hidden, cfg.hidden))
        with torch.no_grad():  # prior: 1% total danger spread over the taxels, not 1% per taxel
            self.tdm.head.bias.fill_(float(np.log(0.01 / n_taxels)))
        self.net = None
        self.S, self.A, self.D = [], [], []

    def update(self, ep: Episode) -> ModulationLayer:
        cfg = self.cfg
        self.S.append(ep.states)
        self.A.append(ep.actions)
        self.D.append(ep.dangers)
        S, A, D = np.concatenate(self.S), np.concatenate(self.A), np.concatenate(self.D).astype(np.float32)
        # augmentation: copies of the states with small noise and the same labels, so the TDM is
        # flat where the data does not vary (its gradient is the modulation's normal)
        rng = np.random.default_rng(self.seed + len(self.S))
        k = cfg.augment
        S = np.concatenate([S] + [S + rng.normal(0, cfg.state_noise, S.shape) for _ in range(k)])
        A, D = np.tile(A, (k + 1, 1)), np.tile(D, (k + 1, 1))
        epochs = max(1, int(np.ceil(cfg.steps * cfg.batch_size / len(S))))
        train_tdm(self.tdm, S, A, D, epochs=epochs, lr=cfg.lr, batch_size=cfg.batch_size, seed=self.seed + len(self.S),
                  progress=False)
        pot = DangerPotential(self.tdm.eval())
        if not self.nstep:
            return ModulationLayer(pot, tangent_gain=cfg.tangent_gain)
        r = cfg.action_range
        pick = np.random.default_rng(self.seed).permutation(len(S))[: cfg.distill_points]
        self.net, _ = distill_nstep(pot, S[pick], A[pick], EulerDynamics(cfg.rollout_dt), UniformPolicy(-r * np.ones(STATE), r * np.ones(STATE)),
                                    NStepConfig(cfg.horizon, cfg.gamma, cfg.samples), state_noise=cfg.state_noise,
                                    epochs=cfg.distill_epochs, seed=self.seed, net=self.net)
        return ModulationLayer(self.net.eval(), tangent_gain=cfg.tangent_gain)


def run_experiment(cfg: TrackingConfig, progress: bool = True) -> dict:
    """All methods x seeds x episodes; returns the results dict (also holds per-episode logs)."""
    torch.set_num_threads(1)
    single_thread_blas()
    results = {"config": asdict(cfg), "runs": {}, "logs": {}}
    total = len(cfg.seeds) * len(cfg.methods) * cfg.episodes
    bar = tqdm(total=total, desc="tracking", disable=not progress)
    for seed in cfg.seeds:
        scene = TrackingScene(cfg, seed)
        results.setdefault("balls", {})[str(seed)] = scene.balls.tolist()
        results["n_taxels"] = scene.design.n_taxels
        for method in cfg.methods:
            rng = np.random.default_rng(seed)
            learner = None if method == "vanilla" else Learner(cfg, scene.design.n_taxels, method == "tdm2", seed)
            layer, rows, logs = None, [], []
            for e in range(cfg.episodes):
                t0 = time.perf_counter()
                ep = run_episode(scene, layer, rng)
                if learner is not None:
                    layer = learner.update(ep)
                rows.append({"episode": e, "contacts": ep.contacts, "onsets": ep.onsets,
                             "tracking_error": ep.tracking_error, "seconds": time.perf_counter() - t0})
                logs.append(ep)
                bar.set_postfix(seed=seed, method=method, contacts=ep.contacts)
                bar.update(1)
            results["runs"].setdefault(method, {})[str(seed)] = rows
            results["logs"].setdefault(method, {})[str(seed)] = logs
    bar.close()
    return results


def summary(results: dict) -> list[dict]:
    """Per method: contacts of the first and last episode and over all (mean over seeds), tracking error."""
    out = []
    for method, by_seed in results["runs"].items():
        c = np.array([[r["contacts"] for r in rows] for rows in by_seed.values()], float)  # (seeds, episodes)
        err = np.array([[r["tracking_error"] for r in rows] for rows in by_seed.values()])
        first_zero = [next((r["episode"] for r in rows if r["contacts"] == 0), None) for rows in by_seed.values()]
        out.append({"method": method, "contacts_first": float(c[:, 0].mean()), "contacts_last": float(c[:, -1].mean()),
                    "contacts_mean": float(c.mean()), "contacts_last_half": float(c[:, c.shape[1] // 2:].mean()),
                    "tracking_error_mm": float(err.mean() * 1e3), "first_zero_episode": first_zero})
    return out


def plot(results: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"vanilla": "tab:red", "tdm": "tab:blue", "tdm2": "tab:green"}
    labels = {"vanilla": "no modulation", "tdm": "TDM modulation", "tdm2": "2-step TDM modulation"}
    fig, ax = plt.subplots(figsize=(6, 4))
    for method, by_seed in results["runs"].items():
        c = np.array([[r["contacts"] for r in rows] for rows in by_seed.values()], float)
        ep = np.arange(1, c.shape[1] + 1)
        ax.plot(ep, c.mean(0), "o-", color=colors.get(method), label=labels.get(method, method))
        ax.fill_between(ep, c.min(0), c.max(0), color=colors.get(method), alpha=0.2)
    ax.set_xlabel("episode")
    ax.set_ylabel("contact ticks per episode")
    ax.set_title(f"UR5 tracking among balls ({len(next(iter(results['runs'].values())))} seeds, min-max band)")
    ax.legend()
    fig.tight_layout()
    paths = [out_dir / "contacts.png"]
    _save(fig, paths[0])
    seed = next(iter(results["balls"]))
    methods = list(results["logs"])
    fig = plt.figure(figsize=(5 * len(methods), 4.5))
    for i, method in enumerate(methods):
        ep: Episode = results["logs"][method][seed][-1]
        ax = fig.add_subplot(1, len(methods), i + 1, projection="3d")
        ax.plot(*ep.ee_desired.T, "k--", lw=1, label="desired")
        ax.plot(*ep.ee.T, color="tab:blue", lw=1.5, label="end effector")
        if len(ep.contact_points):
            ax.scatter(*ep.contact_points.T, color="tab:green", s=8, label="contact points")
        for c in results["balls"][seed]:
            ax.scatter(*c, color="tab:orange", s=120, alpha=0.6)
        ax.set_title(f"{labels.get(method, method)}: {ep.contacts} contact ticks")
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out_dir / "trajectories.png")
    _save(fig, paths[1])
    plt.close("all")
    return paths


def _save(fig, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write(path, buf.getvalue())


def add_arguments(p) -> None:
    p.add_argument("--out", default="results/tracking", help="folder for tracking.json and the plots")
    p.add_argument("--quick", action="store_true", help="reduced run (1 seed, 3 episodes, coarse skin)")
    p.add_argument("--episodes", type=int, help="episodes per method and seed (default 10)")
    p.add_argument("--seeds", type=int, nargs="+", help="seeds (default 0 1 2)")
    p.add_argument("--methods", nargs="+", choices=METHODS, help="methods to run (default all)")
    p.add_argument("--no-progress", action="store_true")


def config_from_args(args) -> TrackingConfig:
    cfg = TrackingConfig.quick() if args.quick else TrackingConfig()
    if args.episodes is not None:
        if args.episodes < 1:
            raise SystemExit(f"--episodes is {args.episodes}; give at least 1")
        cfg.episodes = args.episodes
    if args.seeds:
        cfg.seeds = tuple(args.seeds)
    if args.methods:
        cfg.methods = tuple(args.methods)
    return cfg


def run(args) -> int:
    cfg = config_from_args(args)
    out = Path(args.out)
    t0 = time.perf_counter()
    results = run_experiment(cfg, progress=not args.no_progress)
    table = summary(results)
    doc = {k: v for k, v in results.items() if k != "logs"}
    doc["summary"] = table
    doc["seconds"] = time.perf_counter() - t0
    atomic_write(out / "tracking.json", json.dumps(doc, indent=1))
    paths = plot(results, out)
    for row in table:
        print("  ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    print(f"wrote {out / 'tracking.json'}, " + ", ".join(str(p) for p in paths) + f" in {doc['seconds']:.0f} s")
    return 0
