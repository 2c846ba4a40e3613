"""The skin design: robot reference + FPC modules + boards + taxels (struct of arrays).

Everything between the stages (Blender, MuJoCo, learning, boards) passes a `SkinDesign`.
Taxel geometry is expressed in the frame of the MuJoCo body the taxel rides on; a taxel
frame is a rotation matrix whose columns are the taxel's x, y and z (outward normal) axes.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

STIMULI = ("force", "temperature", "classifier")
"""Stimulus channels a board may report; each has a per-taxel danger threshold."""


class DesignError(ValueError):
    """A skin design (or taxel map file) is invalid; the message names where and how to fix it."""


@dataclass(frozen=True)
class RobotRef:
    """Which robot the skin is designed for.

    kind: "builtin" (name is "ur5" or "panda"), "mjcf" or "urdf" (path to the file: URDF or xacro).
    package_dirs: where `package://NAME/...` and `$(find NAME)` look for ROS packages (a package
    folder, or a folder holding packages), relative to the taxel map or absolute. xacro_args: the
    `name:=value` arguments a xacro file is expanded with.
    """

    kind: str = "builtin"
    name: str = "ur5"
    path: str | None = None
    package_dirs: tuple = ()
    xacro_args: dict = field(default_factory=dict)  # xacro arguments (name -> value) for .xacro files

    def __post_init__(self):
        if isinstance(self.package_dirs, str) or not all(isinstance(d, str) for d in self.package_dirs):
            raise DesignError(f"robot: field 'package_dirs' is {self.package_dirs!r}; give a list of folder paths")
        object.__setattr__(self, "package_dirs", tuple(self.package_dirs))  # a JSON list reads back equal


@dataclass(frozen=True)
class Module:
    """One FPC skin module: a grid of force-sensing resistors on a flexible circuit."""

    id: int
    name: str
    body: str
    template: str = "rect"  # "rect", "strip" or "curve"
    rows: int = 8
    cols: int = 8
    pitch: float = 0.01  # m between taxel centres
    taxel_diameter: float = 0.006  # m
    margin: float = 0.002  # m from the outer taxels to the FPC edge
    min_bend_radius: float = 0.01  # m, the tightest curvature the FPC tolerates
    board: int = 0
    max_strain: float = 0.01  # the in-plane strain the wrapped FPC tolerates (polyimide yields near 3%, traces earlier)
    placement: dict = field(default_factory=dict)  # how it was placed (origin, axes, ...)


@dataclass(frozen=True)
class Board:
    """An interface board digitising up to `capacity` FSR channels."""

    id: int
    name: str
    uid: int  # the board's unique hardware id (matched over serial, not by port order)
    capacity: int = 256


@dataclass
class Taxels:
    """All taxels of a design as arrays of length N (struct of arrays)."""

    ids: np.ndarray  # (N,) int64, unique
    body: np.ndarray  # (N,) int32 index into SkinDesign.bodies
    positions: np.ndarray  # (N, 3) float64, body frame, m
    frames: np.ndarray  # (N, 3, 3) float64, columns x, y, z (outward normal), body frame
    module: np.ndarray  # (N,) int32 module id
    board: np.ndarray  # (N,) int32 board id
    channel: np.ndarray  # (N,) int32 channel on that board
    area: np.ndarray  # (N,) float64 sensing area, m^2
    enabled: np.ndarray  # (N,) bool
    thresholds: dict[str, np.ndarray] = field(default_factory=dict)  # stimulus -> (N,)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) outward normals (the frames' z columns) in the body frame."""
        return self.frames[:, :, 2]

    def subset(self, index) -> "Taxels":
        """The taxels selected by a boolean mask or index array, as a new Taxels."""
        return Taxels(
            **{name: getattr(self, name)[index] for name in ARRAY_FIELDS},
            thresholds={k: v[index] for k, v in self.thresholds.items()},
        )

    @staticmethod
    def concatenate(parts: list["Taxels"]) -> "Taxels":
        """Join several Taxels (for example one per module) into one."""
        if not parts:
            return empty_taxels()
        keys = set(parts[0].thresholds)
        return Taxels(
            **{name: np.concatenate([getattr(p, name) for p in parts]) for name in ARRAY_FIELDS},
            thresholds={k: np.concatenate([p.thresholds[k] for p in parts]) for k in keys},
        )


ARRAY_FIELDS = ("ids", "body", "positions", "frames", "module", "board", "channel", "area", "enabled")
ARRAY_DTYPES = {
    "ids": np.int64, "body": np.int32, "positions": np.float64, "frames": np.float64,
    "module": np.int32, "board": np.int32, "channel": np.int32, "area": np.float64, "enabled": bool,
}
ARRAY_TAILS = {"positions": (3,), "frames": (3, 3)}


def empty_taxels() -> Taxels:
    """A Taxels with zero rows and every field of the right dtype and shape."""
    return Taxels(
        **{name: np.zeros((0,) + ARRAY_TAILS.get(name, ()), ARRAY_DTYPES[name]) for name in ARRAY_FIELDS},
        thresholds={"force": np.zeros(0)},
    )


@dataclass
class SkinDesign:
    """A whole skin: the robot, its skinned bodies, modules, boards and taxels."""

    robot: RobotRef
    bodies: list[str]  # body names that taxel.body indexes into
    modules: list[Module]
    boards: list[Board]
    taxels: Taxels
    coverage: dict = field(default_factory=dict)  # per-body report, filled by the designer
    retired_modules: tuple = ()  # ids of modules this design once had: never given to another module

    @property
    def n_taxels(self) -> int:
        return len(self.taxels)

    def body_of(self, i: int) -> str:
        return self.bodies[int(self.taxels.body[i])]

    def with_taxels(self, taxels: Taxels) -> "SkinDesign":
        return replace(self, taxels=taxels)

    def validate(self, source: str = "design", robot_bodies: set[str] | None = None) -> None:
        """Raise DesignError naming the source, the taxel/module/board and the field at fault."""
        validate_design(self, source, robot_bodies)


def _fail(source: str, where: str, fieldname: str, problem: str, fix: str) -> None:
    raise DesignError(f"{source}: {where}: field '{fieldname}' {problem}; {fix}")


def validate_design(d: SkinDesign, source: str = "design", robot_bodies: set[str] | None = None) -> None:
    """Check shapes, finiteness, frames, ids, channels and bodies of a design."""
    t = d.taxels
    n = len(t.ids)
    for name in ARRAY_FIELDS:
        a = getattr(t, name)
        want = (n,) + ARRAY_TAILS.get(name, ())
        if not isinstance(a, np.ndarray) or a.shape != want:
            got = getattr(a, "shape", type(a).__name__)
            _fail(source, "taxels", name, f"has shape {got}, expected {want}",
                  "give one entry per taxel")
    if "force" not in t.thresholds:
        _fail(source, "taxels", "thresholds.force", "is missing", "give a force threshold (N) per taxel")
    for k, v in t.thresholds.items():
        if k not in STIMULI:
            _fail(source, "taxels", f"thresholds.{k}", "names an unknown stimulus",
                  f"use one of {', '.join(STIMULI)}")
        if np.shape(v) != (n,):
            _fail(source, "taxels", f"thresholds.{k}", f"has shape {np.shape(v)}, expected ({n},)",
                  "give one threshold per taxel")
    for name, a in [("positions", t.positions), ("frames", t.frames), ("area", t.area)] + [
        (f"thresholds.{k}", v) for k, v in t.thresholds.items()
    ]:
        bad = ~np.isfinite(a.reshape(n, -1)).all(axis=1)
        if bad.any():
            _fail(source, f"taxel {int(t.ids[bad.argmax()])}", name, "is not finite (NaN or Inf)",
                  "re-generate the module or fix the number")
    if n and (t.area <= 0).any():
        i = int(np.argmax(t.area <= 0))
        _fail(source, f"taxel {int(t.ids[i])}", "area", f"is {t.area[i]} <= 0", "give a positive area in m^2")
    _check_frames(t, source)
    uniq, counts = np.unique(t.ids, return_counts=True)
    if (counts > 1).any():
        _fail(source, f"taxel {int(uniq[counts > 1][0])}", "id", "is used more than once", "give every taxel its own id")
    if n and ((t.body < 0) | (t.body >= len(d.bodies))).any():
        i = int(np.argmax((t.body < 0) | (t.body >= len(d.bodies))))
        _fail(source, f"taxel {int(t.ids[i])}", "body", f"index {int(t.body[i])} is outside bodies[0:{len(d.bodies)}]",
              "index the 'bodies' list")
    if robot_bodies is not None:
        for b in d.bodies:
            if b not in robot_bodies:
                _fail(source, f"body '{b}'", "bodies", "does not exist in the robot",
                      f"use one of {sorted(robot_bodies)}")
        for m in d.modules:
            if m.body not in robot_bodies:
                _fail(source, f"module {m.id} '{m.name}'", "body", f"'{m.body}' does not exist in the robot",
                      f"use one of {sorted(robot_bodies)}")
    _check_ids(source, "module", [m.id for m in d.modules])
    retired = [i for i in d.retired_modules if not isinstance(i, int) or isinstance(i, bool) or i < 0]
    if retired:
        _fail(source, "retired_modules", "id", f"{retired[0]!r} is not a non-negative whole number",
              "list the ids of deleted modules")
    reused = sorted({m.id for m in d.modules} & set(d.retired_modules))
    if reused:
        m = next(m for m in d.modules if m.id == reused[0])
        _fail(source, f"module {m.id} '{m.name}'", "id", "is retired (a deleted module had it: boards and records "
              "hold it)", "give the module a new id, above every id in 'retired_modules'")
    _check_ids(source, "board", [b.id for b in d.boards])
    _check_ids(source, "board uid", [b.uid for b in d.boards])
    module_ids = {m.id for m in d.modules}
    boards = {b.id: b for b in d.boards}
    for m in d.modules:
        if not 0 < m.max_strain <= 0.2:
            _fail(source, f"module {m.id} '{m.name}'", "max_strain", f"is {m.max_strain}",
                  "give the in-plane strain the FPC tolerates, in (0, 0.2] (e.g. 0.01 for polyimide)")
        if m.board not in boards:
            _fail(source, f"module {m.id} '{m.name}'", "board", f"{m.board} is not a board of the design",
                  "assign the module to an existing board")
    for name, known in (("module", module_ids), ("board", set(boards))):
        col = getattr(t, name)
        bad = ~np.isin(col, np.fromiter(known, dtype=np.int64, count=len(known)))
        if bad.any():
            i = int(bad.argmax())
            _fail(source, f"taxel {int(t.ids[i])}", name, f"{int(col[i])} is not a {name} of the design",
                  f"use an existing {name} id")
    for b in d.boards:
        on = t.board == b.id
        ch = t.channel[on]
        if ch.size and ((ch < 0) | (ch >= b.capacity)).any():
            i = int(np.flatnonzero(on)[np.argmax((ch < 0) | (ch >= b.capacity))])
            _fail(source, f"taxel {int(t.ids[i])}", "channel",
                  f"{int(t.channel[i])} is outside board {b.id} '{b.name}' capacity {b.capacity}",
                  "re-assign channels or use a board with more channels")
        u, c = np.unique(ch, return_counts=True)
        if (c > 1).any():
            _fail(source, f"board {b.id} '{b.name}'", "channel", f"{int(u[c > 1][0])} is used by more than one taxel",
                  "give each taxel on a board its own channel")


def _check_ids(source: str, what: str, ids: list[int]) -> None:
    seen = set()
    for i in ids:
        if i in seen:
            _fail(source, f"{what} {i}", "id", "is used more than once", f"give every {what} its own id")
        seen.add(i)


def _check_frames(t: Taxels, source: str, tol: float = 1e-6) -> None:
    if not len(t.ids):
        return
    R = t.frames
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    if (err > tol).any():
        i = int(err.argmax())
        _fail(source, f"taxel {int(t.ids[i])}", "frame", f"is not orthonormal (error {err[i]:.2e})",
              "give unit, mutually perpendicular x, y, z columns")
    det = np.linalg.det(R)
    if (det < 0).any():
        i = int(np.argmax(det < 0))
        _fail(source, f"taxel {int(t.ids[i])}", "frame", "is left-handed (det = -1)", "use y = z cross x")


def frames_from_normals(normals: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    """Right-handed frames (N,3,3) with z = normal and x = the hint projected onto the tangent plane.

    Where the hint is (nearly) parallel to the normal, any perpendicular axis is used instead.
    """
    z = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    x = np.broadcast_to(x_hint, z.shape).astype(float)
    x = x - np.sum(x * z, axis=1, keepdims=True) * z
    nx = np.linalg.norm(x, axis=1)
    weak = nx < 1e-9
    if weak.any():
        alt = np.where(np.abs(z[weak, 0:1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        alt = alt - np.sum(alt * z[weak], axis=1, keepdims=True) * z[weak]
        x[weak] = alt
        nx[weak] = np.linalg.norm(alt, axis=1)
    x = x / nx[:, None]
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)
