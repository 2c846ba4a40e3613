"""`skinsafe precompile`: compile the numba kernels into numba's on-disk cache now, so that no later process waits
for them. Without it, the first `skinsafe run` after an install spends ~20 s of its warm-up compiling the safety
stack before the robot moves, and every process that starts before the cache holds a kernel compiles it again
(`make test` on a fresh clone: two workers and their subprocesses, ~70 CPU s). `make test` runs it first.

It runs what calls the kernels on the built-in UR5's sample skin: the design (surface kernels, module placement),
the taxel Jacobians, a simulated poke read through the skin, the three layers with a learned danger model (warmed
up as `skinsafe run` does), and the ISO/TS 15066 speed cap; then names any cached kernel of skinsafe still without a
cache entry (exit 1), so that a new kernel cannot stay out of it unnoticed.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PACKAGES = ("skinsafe.core", "skinsafe.hardware")  # where kernels live (the add-on and exporters call core's)


def add_arguments(p) -> None:
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def _design(robot):
    from skinsafe.core.app.design import design_robot
    from skinsafe.core.design.sample import make_sample_design

    design = make_sample_design("ur5", robot=robot)
    design_robot(robot, design.robot, {"module": {"rows": 3, "cols": 3, "pitch": 0.012}, "bodies": design.bodies[:1]})
    return design


def _poke(robot, design) -> None:
    from skinsafe.core.experiments.poke import force_sweep
    from skinsafe.core.safety.retraction import RetractionParams

    force_sweep(design, robot, RetractionParams(), [0.004])


def _stack(robot, design, out: Path) -> None:
    """The runtime's stack with a (random) learned danger model, warmed up as `skinsafe run` does."""
    import torch

    from skinsafe.core.runtime.layers import build_stack
    from skinsafe.core.runtime.loop import warm_up
    from skinsafe.core.safety.tdm import TactileDangerModel, save_tdm

    torch.manual_seed(0)
    nq = robot.model.nq
    path = out / "tdm.pt"
    save_tdm(TactileDangerModel(nq, nq, design.n_taxels, hidden=(16, 16)), path)
    qd_max, qdd_max = np.full(nq, 3.0), np.full(nq, 10.0)
    layers = build_stack(design, robot.model, qd_max, qdd_max, 0.002, tdm_path=str(path))
    warm_up(layers, robot.home, design.taxels.thresholds["force"], 0.002)


def _calls(robot, design, out: Path) -> None:
    """The kernels behind library calls the runs above make in other modes: full Jacobians, one retraction per
    taxel and their merge, and a learned potential over a batch (the warm-up covers its few-row calls)."""
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.safety.potential import DangerPotential, FastPotential
    from skinsafe.core.safety.potential_kernels import FUSED_ROWS
    from skinsafe.core.safety.retraction import RetractionParams, merge, retract_qdot, single_qdots
    from skinsafe.core.safety.tdm import load_tdm

    J = TaxelKinematics(robot.model, design).jacobians(robot.home)[0][:3].copy()
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    params = RetractionParams()
    retract_qdot(J, up, np.ones(3), params)
    merge(single_qdots(J, up, np.ones(3), params), J[:, 2, :], 1e-3)
    pot = FastPotential(DangerPotential(load_tdm(out / "tdm.pt")))
    nq = robot.model.nq
    pot(np.tile(robot.home, (FUSED_ROWS + 1, 1)), np.ones((FUSED_ROWS + 1, nq)))


def _pfl(robot, design) -> None:
    from skinsafe.core.app.pfl import analyse
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.safety.pfl import Person, PFLCap

    qs = robot.home + np.linspace(0.0, 0.3, 3)[:, None]
    analyse(robot, design, ["hand"], trajectory=(np.arange(3.0), qs))
    cap = PFLCap(TaxelKinematics(robot.model, design), ("hand",), fixtures=[((0, 0, 0), (0, 0, 1))])
    cap.observe(Person(("hand",), np.array([[0.4, 0.0, 0.5]]), np.array([[0.4, 0.0, 0.5]]), np.array([0.05]),
                       np.zeros((1, 3))))
    cap(robot.home, np.full(robot.model.nq, 0.5))


def cached_kernels() -> dict[str, list]:
    """Module name -> its kernels that numba keeps in its cache (an inlined kernel has no entry of its own)."""
    import importlib

    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    out = {}
    for pkg in PACKAGES:
        root = Path(importlib.import_module(pkg).__file__).parent
        for path in sorted(root.rglob("*.py")):
            if "numba" not in path.read_text():
                continue
            name = ".".join([pkg, *path.relative_to(root).with_suffix("").parts])
            kernels = [v for v in vars(importlib.import_module(name)).values()
                       if isinstance(v, CPUDispatcher) and v.__module__ == name and not isinstance(v._cache, NullCache)
                       and v.targetoptions.get("inline") != "always"]
            if kernels:
                out[name] = kernels
    return out


def missing() -> list[str]:
    """The cached kernels with no entry in numba's cache."""
    return [f"{module}.{k.__name__}" for module, kernels in cached_kernels().items() for k in kernels
            if not Path(k._cache._cache_file._index_path).is_file()]


def run(args) -> int:
    from skinsafe.core.robot.models import build_ur5

    if args.quiet:
        os.environ["TQDM_DISABLE"] = "1"  # the design's and the poke's progress bars too
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    robot = build_ur5()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        t = time.perf_counter()
        design = _design(robot)
        steps = [("the taxel Jacobians, a simulated poke", lambda: _poke(robot, design)),
                 ("the three layers", lambda: _stack(robot, design, out)),
                 ("their library calls", lambda: _calls(robot, design, out)),
                 ("the ISO/TS 15066 cap", lambda: _pfl(robot, design))]
        say(f"skinsafe precompile: the design ({time.perf_counter() - t:.1f} s)")
        for what, step in steps:
            t = time.perf_counter()
            step()
            say(f"skinsafe precompile: {what} ({time.perf_counter() - t:.1f} s)")
    gone = missing()
    if gone:
        print(f"skinsafe precompile: no cache entry for {', '.join(gone)}: add a call of it to "
              "skinsafe/core/app/precompile.py", file=sys.stderr)
        return 1
    say("skinsafe precompile: every cached kernel is in numba's cache")
    return 0
