"""`skinsafe teleop-key FILE [--force]`: a fresh shared key for teleop (core/runtime/teleop.py).

Written atomically with mode 0600 (only its owner reads it); copy it to the leader's computer over a channel
you trust (scp) and give both sides the same file: `skinsafe run ... --command teleop:PORT --teleop-key FILE`
and `skinsafe teleop-send ... --key FILE`. The key never goes on a command line nor into a record (a record
keeps its path and `key_id`). Exit 0 written, 2 refused (the file exists: --force replaces it).
"""
from __future__ import annotations

import sys

from skinsafe.core.runtime.commands import CommandError
from skinsafe.core.runtime.teleop import make_key


def add_arguments(p) -> None:
    p.add_argument("file", help="where to write the key (JSON, mode 0600)")
    p.add_argument("--force", action="store_true", help="replace an existing key (every leader holding the old one "
                   "is then refused)")


def run(args) -> int:
    try:
        key = make_key(args.file, args.force)
    except (CommandError, OSError) as e:
        print(f"skinsafe teleop-key: {e}", file=sys.stderr)
        return 2
    print(f"skinsafe teleop-key: wrote {key.path} (mode 0600, key id {key.key_id}); give the leader the same file")
    return 0
