"""The taxel map: a skin design as versioned JSON (`schema_version`), validated on load.

Floats are written with Python's shortest round-trip repr, so save -> load is exact.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.ids import converted
from skinsafe.core.skin.model import (
    ARRAY_DTYPES,
    ARRAY_FIELDS,
    ARRAY_TAILS,
    Board,
    DesignError,
    Module,
    RobotRef,
    SkinDesign,
    Taxels,
)

SCHEMA_VERSION = 1
FORMAT = "skinsafe.taxel_map"


def to_dict(design: SkinDesign) -> dict:
    """The JSON-ready dictionary of a design (`retired_modules` only where a module was deleted: a map without
    one reads the same bytes as before the field)."""
    t = design.taxels
    taxels = {name: getattr(t, name).tolist() for name in ARRAY_FIELDS}
    taxels["frames"] = t.frames.reshape(len(t), 9).tolist()
    taxels["thresholds"] = {k: v.tolist() for k, v in t.thresholds.items()}
    return {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "robot": asdict(design.robot),
        "bodies": list(design.bodies),
        "boards": [asdict(b) for b in design.boards],
        "modules": [asdict(m) for m in design.modules],
        "taxels": taxels,
        "coverage": design.coverage,
    } | ({"retired_modules": sorted(design.retired_modules)} if design.retired_modules else {})


def dumps(design: SkinDesign) -> str:
    """The text of the design's taxel-map file (what `save` writes)."""
    return json.dumps(to_dict(design), separators=(",", ":"), allow_nan=False) + "\n"


def sha256(design: SkinDesign) -> str:
    """The hex SHA-256 of the design's taxel-map file: a run's `map_sha256` when it runs with that file."""
    return hashlib.sha256(dumps(design).encode()).hexdigest()


def save(design: SkinDesign, path: str | Path, robot_bodies: set[str] | None = None) -> Path:
    """Validate and write the taxel map atomically (a failed save leaves the old file intact)."""
    design.validate(str(path), robot_bodies)
    return atomic_write(path, dumps(design))


def load(path: str | Path, robot_bodies: set[str] | None = None) -> SkinDesign:
    """Read and validate a taxel map; every failure names the file, the item and the field."""
    path = Path(path)
    src = str(path)
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise DesignError(f"{src}: file not found; check the path") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DesignError(f"{src}: not valid JSON ({e}); re-export the taxel map") from None
    return from_dict(raw, src, robot_bodies)


def from_dict(raw: dict, src: str = "taxel map", robot_bodies: set[str] | None = None) -> SkinDesign:
    """Build and validate a design from the dictionary form."""
    if not isinstance(raw, dict):
        raise DesignError(f"{src}: top level is {type(raw).__name__}, expected an object; re-export the taxel map")
    version = raw.get("schema_version")
    if version != SCHEMA_VERSION:
        raise DesignError(
            f"{src}: field 'schema_version' is {version!r}, this skinsafe reads version {SCHEMA_VERSION}; "
            "re-export the map with this skinsafe or upgrade skinsafe")
    for key in ("robot", "bodies", "boards", "modules", "taxels"):
        if key not in raw:
            raise DesignError(f"{src}: field '{key}' is missing; re-export the taxel map")
    robot = _record(RobotRef, raw["robot"], src, "robot")
    modules = [_record(Module, m, src, f"module #{i}") for i, m in enumerate(raw["modules"])]
    boards = [_record(Board, b, src, f"board #{i}") for i, b in enumerate(raw["boards"])]
    taxels = _taxels(raw["taxels"], src)
    bodies = raw["bodies"]
    if not isinstance(bodies, list) or not all(isinstance(b, str) for b in bodies):
        raise DesignError(f"{src}: field 'bodies' must be a list of body names")
    retired = raw.get("retired_modules", [])
    if not isinstance(retired, list):
        raise DesignError(f"{src}: field 'retired_modules' must be a list of module ids")
    design = SkinDesign(robot, bodies, modules, boards, taxels, raw.get("coverage", {}), tuple(retired))
    design.validate(src, robot_bodies)
    return converted(design, src)


def _record(cls, value, src: str, where: str):
    if not isinstance(value, dict):
        raise DesignError(f"{src}: {where}: expected an object, got {type(value).__name__}")
    names = {f.name for f in fields(cls)}
    unknown = set(value) - names
    if unknown:
        raise DesignError(f"{src}: {where}: unknown field '{sorted(unknown)[0]}'; allowed: {sorted(names)}")
    try:
        rec = cls(**value)
    except TypeError as e:
        raise DesignError(f"{src}: {where}: {e}") from None
    for f in fields(cls):
        v = getattr(rec, f.name)
        want = {"int": int, "float": (int, float), "str": str, "dict": dict}.get(str(f.type))
        if want and not (isinstance(v, want) and not isinstance(v, bool)):
            raise DesignError(f"{src}: {where}: field '{f.name}' is {v!r}, expected {f.type}")
        if isinstance(v, float) and not np.isfinite(v):
            raise DesignError(f"{src}: {where}: field '{f.name}' is not finite")
    return rec


def _taxels(raw: dict, src: str) -> Taxels:
    if not isinstance(raw, dict):
        raise DesignError(f"{src}: field 'taxels' must be an object of arrays")
    arrays = {}
    for name in ARRAY_FIELDS:
        if name not in raw:
            raise DesignError(f"{src}: taxels: field '{name}' is missing; give one entry per taxel")
        try:
            a = np.asarray(raw[name], dtype=float if ARRAY_DTYPES[name] is not bool else object)
        except (ValueError, TypeError):
            raise DesignError(f"{src}: taxels: field '{name}' is not a regular numeric array") from None
        if ARRAY_DTYPES[name] is bool:
            if not all(isinstance(x, bool) for x in a.ravel()):
                raise DesignError(f"{src}: taxels: field 'enabled' must hold true/false values")
            a = a.astype(bool)
        elif np.issubdtype(ARRAY_DTYPES[name], np.integer):
            if a.size and (~np.isfinite(a) | (a != np.round(a))).any():
                raise DesignError(f"{src}: taxels: field '{name}' must hold whole numbers")
            a = a.astype(ARRAY_DTYPES[name])
        if name == "frames":
            if a.ndim != 2 or a.shape[1:] != (9,):
                raise DesignError(f"{src}: taxels: field 'frames' has shape {a.shape}, expected (N, 9)")
            a = a.reshape(-1, 3, 3)
        tail = ARRAY_TAILS.get(name, ())
        if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
            raise DesignError(f"{src}: taxels: field '{name}' has shape {a.shape}, expected (N,{','.join(map(str, tail))})")
        arrays[name] = a
    th = raw.get("thresholds", {})
    if not isinstance(th, dict):
        raise DesignError(f"{src}: taxels: field 'thresholds' must map stimulus names to arrays")
    try:
        thresholds = {k: np.asarray(v, dtype=float) for k, v in th.items()}
    except (ValueError, TypeError):
        raise DesignError(f"{src}: taxels: field 'thresholds' holds a non-numeric array") from None
    return Taxels(**arrays, thresholds=thresholds)
