"""`skinsafe ...` started as an operator would, for the runtime tests."""
import subprocess
import sys


def start_run(args, when_moving=None, timeout=60) -> tuple[int, str, str]:
    """Run the CLI with `args`; `when_moving(proc)` is called once the robot moves. Returns the exit
    code, stdout and stderr; a traceback on stderr fails the test."""
    proc = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    err = []
    for line in proc.stderr:
        err.append(line)
        if "Ctrl-C stops it" in line:
            if when_moving is not None:
                when_moving(proc)
            break
    out, rest = proc.communicate(timeout=timeout)
    err = "".join(err) + rest
    assert "Traceback" not in err, err
    return proc.returncode, out, err
