"""Arrays kept on disk between processes by a content digest (surface pieces, repaired meshes): a key
names what the arrays were made from, so a changed input is a new key, never a stale entry."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np


def cache_dir() -> Path:
    """Where the arrays are kept between processes: $SKINSAFE_PIECES, else the folder `pieces`
    in $SKINSAFE_CACHE or ~/.cache/skinsafe."""
    if os.environ.get("SKINSAFE_PIECES"):
        return Path(os.environ["SKINSAFE_PIECES"])
    return Path(os.environ.get("SKINSAFE_CACHE") or Path.home() / ".cache" / "skinsafe") / "pieces"


def load_pieces(key: str) -> list[np.ndarray] | None:
    """The arrays (n_i, 3) kept under `key` (`cache_dir`), or None."""
    try:
        with np.load(cache_dir() / f"{key}.npz") as z:
            return np.split(z["points"], z["ends"][:-1]) if len(z["ends"]) else []
    except (OSError, ValueError, KeyError):
        return None


def save_pieces(key: str, pieces: list[np.ndarray]) -> None:
    """Written to a temporary file and renamed: a reader never sees half a file; a cache that
    cannot be written is only slower."""
    folder = cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, suffix=".npz", delete=False) as f:
            np.savez(f, points=np.concatenate(pieces) if pieces else np.zeros((0, 3)),
                     ends=np.cumsum([len(p) for p in pieces], dtype=np.int64))
        os.replace(f.name, folder / f"{key}.npz")
    except OSError:
        pass
