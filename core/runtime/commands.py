"""Command sources: what the operator asks for, as the planned joint velocity of each tick.

- `hold`: zero velocity (the robot stays where it is, and where a retraction leaves it);
- `trajectory:FILE`: joint positions over time from a CSV file (format below), tracked from the
  first tick (`TrajectorySource`: `qd_d(t) + gain * clip(q_d - q, +-max_error)`); after its last
  row it holds the last position;
- `teleop:[HOST:]PORT`: joint targets streamed over UDP by the leader alone, signed, as the paper's
  leader arm (core/runtime/teleop.py: the datagram, the key, what is refused); the newest target is
  tracked the same way; nothing before the first datagram.

Trajectory CSV: a header `t,<joint name>,...` naming every joint of the robot once (any order),
then one row per sample: time in s from the start (the first 0, strictly increasing) and joint
positions in rad (m for a slide joint); `#` starts a comment line. Refused with the row and column
named: a missing or unknown joint, a non-number or non-finite value, time not increasing, a
position outside the robot's range, a step faster than its velocity limit.

Staleness: `age()` is how old the source's data is (host clock). Hold and trajectory are computed
in the loop each tick (age 0); teleop's age is the time since its last accepted datagram, and the
runtime stops the robot when it exceeds `stale_s`.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from skinsafe.core.safety.stack import TrajectorySource


class CommandError(ValueError):
    """A command source that cannot be used: one line naming what is wrong and the fix."""


class Hold:
    spec, stale_s = "hold", None
    refused = 0  # datagrams refused (teleop)
    intrusion = None  # teleop: a sender that keeps trying (core/runtime/teleop.py `Intrusion`)

    def __init__(self, n: int):
        self.zero = np.zeros(n)

    def start(self, q0: np.ndarray) -> None:
        pass

    def __call__(self, t: float, q: np.ndarray) -> np.ndarray:
        return self.zero

    def age(self) -> float:
        return 0.0

    def close(self) -> None:
        pass


class Trajectory(Hold):
    """Joint positions over time from a CSV file (module docstring), tracked."""

    def __init__(self, path: str | Path, joint_names: list[str], limits: dict[str, np.ndarray]):
        super().__init__(len(joint_names))
        self.spec = f"trajectory:{path}"
        self.times, self.q = read_trajectory(path, joint_names, limits)
        self.rates = np.diff(self.q, axis=0) / np.diff(self.times)[:, None]
        self.track = TrajectorySource(self._at)

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def _at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        if t >= self.times[-1]:
            return self.q[-1], self.zero
        t = max(t, 0.0)
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        w = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        return self.q[i] + w * (self.q[i + 1] - self.q[i]), self.rates[i]

    def __call__(self, t: float, q: np.ndarray) -> np.ndarray:
        return self.track(t, q)


def read_trajectory(path: str | Path, joint_names: list[str], limits: dict[str, np.ndarray]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(times (T,), positions (T, n) in the robot's joint order) of a trajectory CSV, validated."""
    path = Path(path)
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as e:
        raise CommandError(f"trajectory {path}: cannot read it ({e})") from None
    rows = list(csv.reader(lines))
    if not rows:
        raise CommandError(f"trajectory {path}: empty; give a header 't,{','.join(joint_names)}' and rows")
    head = [h.strip() for h in rows[0]]
    if not head or head[0] != "t":
        raise CommandError(f"trajectory {path}: the header's first column is {head[:1]}, not 't'; start it "
                           f"with 't,{','.join(joint_names)}'")
    cols = head[1:]
    unknown = [c for c in cols if c not in joint_names]
    missing = [j for j in joint_names if j not in cols]
    if unknown or missing or len(set(cols)) != len(cols):
        raise CommandError(f"trajectory {path}: header columns {cols} do not name each joint once (unknown "
                           f"{unknown}, missing {missing}); the robot's joints are {joint_names}")
    data = np.empty((len(rows) - 1, len(head)))
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != len(head):
            raise CommandError(f"trajectory {path}: row {r} has {len(row)} values, the header {len(head)}")
        for c, v in enumerate(row):
            try:
                data[r - 2, c] = float(v)
            except ValueError:
                raise CommandError(f"trajectory {path}: row {r}, column '{head[c]}': {v!r} is not a number") from None
            if not math.isfinite(data[r - 2, c]):
                raise CommandError(f"trajectory {path}: row {r}, column '{head[c]}': {v} is not finite")
    if len(data) < 2:
        raise CommandError(f"trajectory {path}: {len(data)} rows; give at least two samples")
    t = data[:, 0]
    if t[0] != 0:
        raise CommandError(f"trajectory {path}: row 2: t = {t[0]}; the first sample is at t = 0")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        raise CommandError(f"trajectory {path}: row {bad[0] + 3}: t = {t[bad[0] + 1]} does not increase "
                           f"(previous {t[bad[0]]}); sort the rows by time")
    q = data[:, [1 + cols.index(j) for j in joint_names]]
    for name, test, what in (("q_min", lambda x, lim: x < lim, "below"), ("q_max", lambda x, lim: x > lim, "above")):
        out = test(q, limits[name][None])
        if out.any():
            r, j = np.argwhere(out)[0]
            raise CommandError(f"trajectory {path}: row {r + 2}, joint '{joint_names[j]}': {q[r, j]:.4f} is {what} "
                               f"the robot's range ({limits[name][j]:.4f})")
    speed = np.abs(np.diff(q, axis=0)) / np.diff(t)[:, None]
    over = speed > limits["qd_max"][None]
    if over.any():
        r, j = np.argwhere(over)[0]
        raise CommandError(f"trajectory {path}: rows {r + 2}-{r + 3}, joint '{joint_names[j]}': {speed[r, j]:.3f} "
                           f"rad/s, above the robot's limit {limits['qd_max'][j]:.3f}; slow that segment down")
    return t, q


def command_source(spec: str, joint_names: list[str], limits: dict[str, np.ndarray], stale_s: float = 0.1,
                   key=None, leader: str | None = None):
    """The source a `--command` spec names (module docstring); teleop's `key` (core/runtime/teleop.py `TeleopKey`)
    and `leader` (HOST[:PORT]); either given to another source is refused."""
    kind, _, arg = spec.partition(":")
    if kind != "teleop" and (key is not None or leader):
        raise CommandError(f"--teleop-key and --teleop-leader are for --command teleop:[HOST:]PORT, not {spec!r}")
    if kind == "hold" and not arg:
        return Hold(len(joint_names))
    if kind == "trajectory" and arg:
        return Trajectory(arg, joint_names, limits)
    if kind == "teleop" and arg:
        if not (math.isfinite(stale_s) and stale_s > 0):
            raise CommandError(f"command timeout {stale_s} s: give a positive number of seconds")
        from skinsafe.core.runtime.teleop import NO_KEY, Teleop

        return Teleop(arg, joint_names, limits, stale_s, key or NO_KEY, leader)
    raise CommandError(f"--command {spec!r}: use hold, trajectory:FILE.csv or teleop:[HOST:]PORT")
