"""A run is a pure function of (code, configuration, seed): the same small maze and tracking runs in two fresh
processes, one on two Ray workers (three maze tasks on two: a worker takes a second task after its first, and nothing
may leak from one to the next) and one with no Ray (`workers=0`: every task in turn in one process), give identical result rows."""
import json
import subprocess
import sys

from skinsafe.core.experiments import runner

SCRIPT = r"""
import json, sys, tempfile
from dataclasses import asdict

import ray

from skinsafe.core.experiments import runner
from skinsafe.core.experiments.maze import run_row
from skinsafe.core.experiments.maze_runs import run_one
from skinsafe.core.experiments.tracking_runs import RunConfig, run_method

conf = json.loads(json.dumps(asdict(RunConfig.quick())))
conf["episodes"] = 2
maze = [{"method": m, "seed": 3, "episodes": 2, "max_steps": 30, "agent_kw": kw}
        for m, kw in (("AC-TDM", {}), ("SAC", {}), ("SQRL", {"offline_transitions": 80, "pretrain_steps": 10}))]
track = [{"method": "tdm2", "seed": 0, "config": dict(conf, labels="binary")}]
with tempfile.TemporaryDirectory() as tmp:
    a = runner.run_tasks(run_one, maze, tmp + "/m", workers=int(sys.argv[1]), progress=False, keep_ray=True)
    b = runner.run_tasks(run_method, track, tmp + "/t", workers=int(sys.argv[1]), progress=False)
    ray.shutdown()
rows = [dict(run_row(r), cpu_seconds=None, costs=r["costs"], returns=r["returns"], fits=[{k: v for k, v in f.items() if k != "seconds"} for f in r["tdm_fits"]]) for r in a]
rows += [{k: v for k, v in row.items() if k != "seconds"} for r in b for row in r["rows"]]
print(json.dumps(rows))
"""


def _rows(*workers: int) -> list[list]:
    """The rows of one fresh process per entry of `workers`, the processes side by side (Ray's start-up waits)."""
    procs = [subprocess.Popen([sys.executable, "-c", SCRIPT, str(w)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for w in workers]
    out = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=300)
        assert p.returncode == 0, stderr[-2000:]
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def test_small_maze_and_tracking_runs_repeat_exactly_across_processes_and_workers():
    two, here = _rows(2, 0)
    assert two == here
    maze, track = two[:3], two[3:]
    assert [r["method"] for r in maze] == ["AC-TDM", "SAC", "SQRL"] and len(track) == 2
    assert maze[0]["fits"] and maze[0]["fits"][0]["train_loss"] > 0  # the TDM's fit records repeat to the last digit
    assert maze[2]["offline_contacts"] > 0 and track[1]["fit"]["steps"] > 0  # the offline phase and the n-step fit ran
    assert track[0]["contacts"] > 20  # vanilla's first episode touches the balls


def test_result_provenance_names_code_and_library_versions():
    p = runner.provenance()
    assert set(p["versions"]) == {"torch", "mujoco", "numba", "numpy"} and len(p["code_sha1"]) == 40
    import numpy
    import torch

    assert p["versions"]["numpy"] == numpy.__version__ and p["versions"]["torch"].split("+")[0] == torch.__version__.split("+")[0]
