"""`skinsafe replay DIR [--map MAP]` (a `run --record` folder, or a FILE.mcap of an earlier skinsafe): re-run the layers on a record, report the largest command difference.

Exit codes: 0 replayed, every command reproduced within `--tol` and the record complete; 1 a difference
above it, or an incomplete record (ticks dropped by the recorder); 2 a record or map that cannot be read.
"""
from __future__ import annotations

import json
import math
import sys

from skinsafe.core.runtime.layers import stack_from_config
from skinsafe.core.runtime.replay import ReplayError, replay


def add_arguments(p) -> None:
    p.add_argument("record", help="a record of `skinsafe run --record`: its folder (or a bare FILE.mcap of an earlier skinsafe)")
    p.add_argument("--map", help="the taxel map the run used (default: the path in the record)")
    p.add_argument("--tol", type=float, default=1e-9, help="largest difference counted as floating-point noise (rad/s)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args) -> int:
    if not (math.isfinite(args.tol) and args.tol >= 0):
        print(f"skinsafe replay: --tol {args.tol}: give a finite difference >= 0 in rad/s, e.g. 1e-9", file=sys.stderr)
        return 2
    try:
        r = replay(args.record, stack_from_config, args.map)
    except (ReplayError, ValueError) as e:
        print(f"skinsafe replay: {e}", file=sys.stderr)
        return 2
    ok = r["max_abs_diff"] <= args.tol and r["complete"]
    if args.json:
        print(json.dumps(r | {"ok": ok}))
    else:
        print(f"replay {args.record}: {r['ticks']} ticks, largest difference from the recorded commands "
              f"{r['max_abs_diff']:.3g} rad/s ({'within' if r['max_abs_diff'] <= args.tol else 'ABOVE'} {args.tol:g}); "
              + ("record complete" if r["complete"] else f"record INCOMPLETE: {r['gaps']} gap(s) of dropped ticks"))
    return 0 if ok else 1
