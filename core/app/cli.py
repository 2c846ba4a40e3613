"""The `skinsafe` command line.

Each subcommand lives in its own module, imported only when used (so `skinsafe deploy` never
loads torch or bpy). A command module exposes `add_arguments(parser)` and `run(args) -> int`.
A benchmark module exposes `add_arguments(parser)` (optional) and `rows(args) -> list[dict]`;
`skinsafe bench NAME` prints the rows as a table, or as one JSON list with `--json`; `--save FILE`
also writes them with the command line and the machine (results/bench/NAME.json: README tables).
"""
from __future__ import annotations

import sys


def _interrupted(kind, value, tb, default=sys.excepthook) -> None:
    """Ctrl-C while this module still loads (before main's handler is in place): one line, no traceback, exit 130
    (nothing has run yet that an exit without clean-up could leave half-done)."""
    if issubclass(kind, KeyboardInterrupt):
        print("skinsafe: interrupted", file=sys.stderr, flush=True)
        import os

        os._exit(130)
    default(kind, value, tb)


if __name__ == "__main__" or sys.argv and sys.argv[0].endswith("skinsafe"):  # the command, not an importing program
    sys.excepthook = _interrupted

import signal  # noqa: E402  (after the hook: nothing else loads before main installs its Ctrl-C handler)

COMMANDS = {
    "demo": ("skinsafe.core.app.demo", "run the whole product on the bundled sample scene and write a report"),
    "design": ("skinsafe.core.app.design", "design a skin on any robot (built-in, URDF, xacro, MJCF) from a layout spec"),
    "sample": ("skinsafe.core.design.sample", "generate the sample skin on a built-in robot and save its taxel map"),
    "check": ("skinsafe.core.app.check", "validate a taxel map against its robot and print a summary"),
    "export": ("skinsafe.exporters.cli_export", "export a skin design to a MuJoCo scene (MJCF) and taxel map"),
    "poke": ("skinsafe.core.experiments.poke", "poke taxels in simulation and plot the retraction (paper Fig. 8/12, Fig. 7)"),
    "deploy": ("skinsafe.hardware.cli_deploy", "push a taxel map to the interface boards over serial and verify it"),
    "stream": ("skinsafe.hardware.cli_stream", "stream readings from the boards, mapped to taxels"),
    "emulate": ("skinsafe.hardware.cli_emulate", "run a board emulator on a pseudo-terminal"),
    "run": ("skinsafe.core.app.run", "the safety runtime: boards -> the three layers -> a robot (sim or FR3), with watchdogs"),
    "teleop-key": ("skinsafe.core.app.teleop_key", "make a shared key (mode 0600) for `run --command teleop:` and its "
                   "leader"),
    "teleop-send": ("skinsafe.core.app.teleop_send", "a stand-in leader arm: a trajectory as signed teleop datagrams"),
    "view": ("skinsafe.core.app.view", "see a run live (`run --view` stream) or a record in the browser"),
    "faults": ("skinsafe.core.app.runtime_faults", "inject each fault kind at its source into short runs and time "
               "onset -> zero command (`bench runtime --faults` summarises it)"),
    "replay": ("skinsafe.core.app.replay", "re-run the layers on a `run --record` MCAP and compare the commands"),
    "pfl": ("skinsafe.core.app.pfl", "ISO/TS 15066: effective mass and safe approach speed per taxel, at a pose or along a trajectory"),
    "trade": ("skinsafe.core.app.trade", "sweep speed-vs-accuracy knobs (Ray) and plot the Pareto front"),
    "precompile": ("skinsafe.core.app.precompile", "compile the numba kernels into numba's cache now (once per "
                   "install: no later run waits for them)"),
    "readme": ("skinsafe.core.app.readme", "fill the README's figures from the results files (make readme-figures)"),
}
EXPERIMENTS = {
    "maze": ("skinsafe.core.app.experiment_maze", "strategy layer: safe RL in the maze (paper Fig. 9)"),
    "tracking": ("skinsafe.core.app.experiment_tracking", "modulation layer: UR5 tracking among balls (Fig. 11)"),
    "desk": ("skinsafe.core.experiments.scenes", "retraction toward a desk stopped by modulation (Fig. 14)"),
    "collaboration": ("skinsafe.core.experiments.collaboration", "a person beside a delivery: ISO/TS 15066 per contact (Fig. 15)"),
}
BENCHES = {
    "jacobians": ("skinsafe.core.bench.jacobians", "batched taxel Jacobians vs a per-taxel loop"),
    "design": ("skinsafe.core.bench.design", "placing modules and re-generating one after a move"),
    "fab": ("skinsafe.core.app.bench_fab", "a buildable skin on robots' own descriptions: strain, round trip, coverage, fab files"),
    "sensing": ("skinsafe.core.bench.sensing", "vectorised skin readout vs per-taxel touch sensors"),
    "retraction": ("skinsafe.core.bench.retraction", "one defensiveness tick vs a loop"),
    "modulation": ("skinsafe.core.bench.modulation", "modulation tick and full three-layer tick"),
    "import": ("skinsafe.core.bench.robot_import", "a robot's own description in, a full-arm skin on its real surface"),
    "pfl": ("skinsafe.core.bench.pfl", "the ISO/TS 15066 speed cap tick vs a per-taxel loop"),
    "safety": ("skinsafe.core.bench.safety", "correctness audit: no-push, limits, fail-safe on random contact sets"),
    "serial": ("skinsafe.core.bench.serial_link", "deploy and stream decoding over a pseudo-terminal"),
    "runtime": ("skinsafe.core.bench.runtime", "skinsafe run closed-loop: loop rate, latency, reaction, faults"),
    "viewers": ("skinsafe.core.bench.viewers", "the live view in headless Chromium: viser vs Rerun at 16,384 taxels"),
}


def _load(module: str, what: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name == module:
            sys.exit(f"skinsafe: {what} is not available in this installation ({module} missing)")
        raise


def print_rows(rows: list[dict], as_json: bool) -> None:
    """A benchmark's rows as a JSON list or an aligned table."""
    if as_json:
        import json

        print(json.dumps(rows))
        return
    if not rows:
        print("(no rows)")
        return
    keys = list(dict.fromkeys(k for r in rows for k in r))
    cells = [[_fmt(r.get(k, "")) for k in keys] for r in rows]
    width = [max(len(k), *(len(c[i]) for c in cells)) for i, k in enumerate(keys)]
    print("  ".join(k.rjust(w) for k, w in zip(keys, width)))
    for c in cells:
        print("  ".join(v.rjust(w) for v, w in zip(c, width)))


def save_rows(path: str, rows: list[dict], command: str) -> None:
    """A benchmark's rows as a results file: the rows, the command that made them, when and under what load."""
    import json
    import os
    import platform
    import time

    from skinsafe.core.skin.files import atomic_write

    meta = {"command": command, "date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count(),
            "load_average": [round(x, 1) for x in os.getloadavg()], "machine": platform.machine()}
    atomic_write(path, json.dumps({**meta, "rows": rows}, indent=1))


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def build_parser():
    import argparse

    p = argparse.ArgumentParser(prog="skinsafe", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, helptext) in COMMANDS.items():
        sub.add_parser(name, help=helptext, add_help=False)
    ex = sub.add_parser("experiment", help="run one of the paper's experiments")
    ex.add_argument("name", choices=sorted(EXPERIMENTS), help="; ".join(f"{k}: {v[1]}" for k, v in EXPERIMENTS.items()))
    b = sub.add_parser("bench", help="measure speed (and accuracy) against a simple reference")
    b.add_argument("name", choices=sorted(BENCHES), help="; ".join(f"{k}: {v[1]}" for k, v in BENCHES.items()))
    return p


def main(argv: list[str] | None = None) -> int:
    """Run one command; Ctrl-C anywhere (even while a command module is still importing, where
    a C extension may turn the interrupt into an ImportError) ends with exit code 130 and one
    line, never a traceback."""
    interrupted = []

    def on_sigint(signum, frame):
        interrupted.append(True)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        try:
            code = _main(argv)
        except BaseException:
            if not interrupted:
                raise
        if not interrupted:  # (or a Ctrl-C some code swallowed: importlib ignores what its lock callback raises)
            return code
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # one Ctrl-C, one clean exit
        print("skinsafe: interrupted", file=sys.stderr)
        _handled_interrupt()
        return 130
    finally:
        if not interrupted:  # the `skinsafe` command is ending: a late Ctrl-C must not interrupt its shutdown
            signal.signal(signal.SIGINT, signal.SIG_IGN if sys.excepthook is _interrupted else previous)


def _handled_interrupt() -> None:
    """Tell CPython the KeyboardInterrupt was handled: one raised inside code a C extension ran with PyRun_*
    (pybind11's exec while mujoco or torch import) sets `_Py_UnhandledKeyboardInterrupt` even when caught, and
    at exit CPython then kills itself with SIGINT (exit -2, seen 1 in 40 interrupts during imports) instead of
    exiting 130. Python 3.11 exports the flag; elsewhere this does nothing."""
    import contextlib
    import ctypes

    with contextlib.suppress(ValueError, AttributeError):
        ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt").value = 0


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    cmd = argv[0]
    if cmd in COMMANDS:
        module, helptext = COMMANDS[cmd]
        return _run_module(_load(module, f"'{cmd}'"), f"skinsafe {cmd}", helptext, argv[1:], cmd)
    if cmd in ("experiment", "bench") and len(argv) > 1 and not argv[1].startswith("-"):
        table = EXPERIMENTS if cmd == "experiment" else BENCHES
        name = argv[1]
        if name not in table:
            parser.error(f"unknown {cmd} '{name}'; choose from {', '.join(sorted(table))}")
        module, helptext = table[name]
        return _run_module(_load(module, f"{cmd} '{name}'"), f"skinsafe {cmd} {name}", helptext, argv[2:], name,
                           bench=cmd == "bench")
    parser.parse_args(argv)  # prints usage and exits for anything else
    return 2


def module_args(mod, prog: str, helptext: str, argv: list[str], name: str, bench: bool = False):
    """Parse `argv` with the module's own arguments (the demo uses this to run commands in-process)."""
    return module_parser(mod, prog, helptext, name, bench).parse_args(argv)


def module_parser(mod, prog: str, helptext: str, name: str, bench: bool = False):
    """The argument parser of one command module (its own arguments, plus --json/--save for a bench)."""
    import argparse

    p = argparse.ArgumentParser(prog=prog, description=helptext)
    if bench:
        p.add_argument("--json", action="store_true", help="print one JSON list of flat rows")
        p.add_argument("--save", metavar="FILE", help="also write the rows, the command and the machine's load to "
                                                      "FILE (results/bench/NAME.json feeds the README's tables)")
    p.set_defaults(command_name=name)  # one module may serve several names
    if hasattr(mod, "add_arguments"):
        mod.add_arguments(p)
    return p


def reference_markdown() -> str:
    """Every command's `--help`, as Markdown (the docs' CLI reference is generated from it)."""
    import importlib
    import os
    from unittest import mock

    parts = []
    with mock.patch.dict(os.environ, {"COLUMNS": "110"}):  # argparse wraps at the terminal's width: one page anywhere
        parts += ["```text", build_parser().format_help().rstrip(), "```"]
        for prefix, table in [("", COMMANDS), ("experiment ", EXPERIMENTS), ("bench ", BENCHES)]:
            for name, (module, helptext) in sorted(table.items()):
                prog = f"skinsafe {prefix}{name}"
                parser = module_parser(importlib.import_module(module), prog, helptext, name, bench=prefix == "bench ")
                parts += [f"### `{prog}`", "", "```text", parser.format_help().rstrip(), "```", ""]
    return "\n".join(parts)


def _run_module(mod, prog: str, helptext: str, argv: list[str], name: str, bench: bool = False) -> int:
    import warnings

    from skinsafe.core.skin.model import DesignError  # here: the CLI starts (and takes Ctrl-C) before numpy loads

    args = module_args(mod, prog, helptext, argv, name, bench)
    warnings.showwarning = lambda msg, cat, *a, **k: print(f"skinsafe {name}: warning: {msg}", file=sys.stderr)
    try:
        if bench:
            rows = mod.rows(args)
            print_rows(rows, args.json)
            if args.save:
                save_rows(args.save, rows, f"skinsafe bench {name} {' '.join(argv)}".strip())
            return 0
        return int(mod.run(args) or 0)
    except (DesignError, FileNotFoundError) as e:  # FileNotFoundError: also a missing system part (core/system.py)
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a folder that cannot be made or written: name it, no traceback
        where = f"{e.filename}: " if e.filename else ""
        print(f"skinsafe {name}: error: {where}{e.strerror or e}; choose a folder you can write to", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
