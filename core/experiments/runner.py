"""Experiments as Ray tasks: one task per (method, seed), results cached per task.

`run_tasks(fn, tasks, cache)` runs `fn(**task)` for every task dict as a Ray task (one CPU each).
Each finished task is written at once to `cache/<method>_s<seed>[_<digest>].json` (atomically) together with
the task it ran, a digest of every skinsafe source file loaded where it ran and the versions of the
libraries that decide its numbers (`VERSIONED`), so a restarted run reuses every task whose file holds
the same task (the same method, seed and configuration) run by the same code on the same libraries,
and only runs the rest (a changed default in an agent re-runs its tasks). A run is a pure function of
(code, configuration, seed): every task runs with torch and BLAS on one thread (`_one_thread`), and
`provenance()` (the hash of the package's sources and those versions) goes into every result file. A
task given twice in one call runs once. Ray is local by default (`workers` CPUs, a private instance that
stops at the end); `address` joins a cluster instead (every node needs skinsafe installed); `workers=0`
runs the tasks one after another in this process, with no Ray (a debugger reaches them; a smoke run skips
Ray's start, seconds more than its tasks): the same rows, as tests/experiments/test_determinism.py checks.
Progress is shown as tasks finish.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Callable

from tqdm.auto import tqdm

from skinsafe.core.skin.files import atomic_write


def task_file(cache: Path, task: dict) -> Path:
    """`<method>_s<seed>.json`, with a short digest of the run's configuration when it has one (`agent_kw`,
    `config`), so configurations and variants never share a file (the task itself is checked on reuse)."""
    conf = {k: task[k] for k in ("agent_kw", "config") if task.get(k)}
    tag = "_" + hashlib.sha1(json.dumps(conf, sort_keys=True).encode()).hexdigest()[:8] if conf else ""
    return Path(cache) / f"{task['method']}_s{task['seed']}{tag}.json"


def cached(cache: Path, task: dict) -> dict | None:
    """The stored result of exactly this task, or None (missing, unreadable or another configuration)."""
    path = task_file(cache, task)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if (doc.get("task") != json.loads(json.dumps(task)) or not _unchanged(doc.get("sources"))
            or doc.get("versions") != versions()):
        return None
    return doc.get("result")


ROOT = Path(__file__).resolve().parents[2]  # the folder the `skinsafe` package maps to
VERSIONED = ("torch", "mujoco", "numba", "numpy")  # the libraries whose version can change a run's numbers
ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}


def versions() -> dict[str, str]:
    """{library: installed version} of `VERSIONED`."""
    from importlib.metadata import version

    return {name: version(name) for name in VERSIONED}


def code_hash() -> str:
    """sha1 over the path and bytes of every .py file of `skinsafe.core` (the code an experiment runs)."""
    h = hashlib.sha1()
    for path in sorted((ROOT / "core").rglob("*.py")):
        h.update(path.relative_to(ROOT).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def provenance() -> dict:
    """What a result was computed with: `code_sha1` (`code_hash`), the library `versions`, one thread."""
    return {"code_sha1": code_hash(), "versions": versions(), "threads": 1}


def _digest(path: Path) -> str | None:
    try:
        return hashlib.sha1(path.read_bytes()).hexdigest()
    except OSError:
        return None


def loaded_sources() -> dict[str, str]:
    """{source file relative to the package: sha1} of every skinsafe module loaded in this process."""
    out = {}
    for name, mod in list(sys.modules.items()):
        f = getattr(mod, "__file__", None)
        if name.startswith("skinsafe.") and f and f.endswith(".py"):
            path = Path(f).resolve()
            if path.is_relative_to(ROOT):
                out[path.relative_to(ROOT).as_posix()] = _digest(path)
    return out


def _unchanged(sources) -> bool:
    """Whether a result's recorded sources are all still the same (none recorded: not known, so no)."""
    return bool(sources) and all(_digest(ROOT / p) == h for p, h in sources.items())


def _one_thread() -> None:
    """torch and BLAS on one thread in this process (a run's numbers must not depend on thread counts)."""
    import torch

    from skinsafe.core.realtime import single_thread_blas

    torch.set_num_threads(1)
    single_thread_blas()


def traced(fn: Callable[..., dict], task: dict) -> tuple[dict, dict[str, str], dict[str, str]]:
    """`fn(**task)` on one thread, the skinsafe sources it ran with (`loaded_sources` after it) and `versions`."""
    _one_thread()
    result = fn(**task)
    return result, loaded_sources(), versions()


def _start_ray(ray, address: str | None, workers: int | None, tries: int = 3) -> None:
    """Start (or join) Ray; on an overloaded machine a local raylet can miss its start-up timeout, so a
    local start is retried, and a final failure is one clear message (finished tasks stay cached)."""
    for k in range(1 if address else tries):
        try:
            if address:
                ray.init(address=address, log_to_driver=False, runtime_env={"env_vars": ONE_THREAD})
            else:
                n = int(workers or min(2, os.cpu_count() or 1))
                ray.init(address="local", num_cpus=n, include_dashboard=False, log_to_driver=False,
                         object_store_memory=128 * 2 ** 20, runtime_env={"env_vars": ONE_THREAD})
            return
        except Exception as e:  # noqa: BLE001 - Ray raises plain Exception for a start-up timeout
            ray.shutdown()
            last = e
            time.sleep(5 * (k + 1))
    raise SystemExit(f"Ray could not start ({'joining ' + address if address else 'locally'}): {last}. On a busy machine "
                     "re-run the same command (finished tasks are reused) or set RAY_raylet_start_wait_time_s=180.")


def run_tasks(fn: Callable[..., dict], tasks: list[dict], cache: str | Path, address: str | None = None,
              workers: int | None = None, progress: bool = True, desc: str = "tasks", fresh: bool = False,
              cost: Callable[[dict], float] | None = None, keep_ray: bool = False) -> list[dict]:
    """Results of `fn(**task)` for every task, in the order given (module doc). `fn` must be a
    module-level function (Ray pickles it by reference); `fresh` ignores cached results. `cost`, an
    estimate of a task's run time, submits the longest first (so that no long task starts last and
    runs alone on an otherwise idle machine). `keep_ray` leaves a Ray it started running for the next
    stage (the caller then ends it with `ray.shutdown()`)."""
    if workers is not None and workers < 0:
        raise SystemExit(f"--workers {workers}: give 0 (the tasks in this process) or more")
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    results: list[dict | None] = [None if fresh else cached(cache, t) for t in tasks]
    first = {}  # a task given twice (two replicates choosing the same configuration) runs once
    for i, t in enumerate(tasks):
        first.setdefault(json.dumps(t, sort_keys=True), i)
    same = [first[json.dumps(t, sort_keys=True)] for t in tasks]
    todo = [i for i, r in enumerate(results) if r is None and same[i] == i]
    if cost is not None:
        todo.sort(key=lambda i: -cost(tasks[i]))
    bar = tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc=desc, disable=not progress, file=sys.stderr)
    def done(i: int, result: dict, sources: dict, libs: dict) -> None:
        results[i] = result
        atomic_write(task_file(cache, tasks[i]), json.dumps({"task": tasks[i], "result": result, "sources": sources,
                                                             "versions": libs}))
        bar.set_postfix_str(f"{tasks[i]['method']} seed {tasks[i]['seed']}")
        bar.update()

    if todo and workers == 0 and not address:
        for i in todo:
            done(i, *traced(fn, tasks[i]))
    elif todo:
        import ray

        started = not ray.is_initialized()
        if started:
            _start_ray(ray, address, workers)
        try:
            remote = ray.remote(num_cpus=1)(traced)
            refs = {remote.remote(fn, tasks[i]): i for i in todo}
            pending = list(refs)
            while pending:
                finished, pending = ray.wait(pending, num_returns=1)
                for ref in finished:
                    done(refs[ref], *ray.get(ref))
        finally:
            if started and not keep_ray:
                ray.shutdown()
    bar.close()
    return [results[j] for j in same]
