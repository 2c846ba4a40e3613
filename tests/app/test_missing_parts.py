"""Every `skinsafe` command that needs a part of the machine pip does not install (a Chromium, franky-sim's
environment) ends, where the part is missing, with exit code 2 and one line naming it and how to get it: never a
traceback, and before any work starts. The part is hidden through the variable the code honours
(SKINSAFE_CHROMIUM, SKINSAFE_FRANKY_PYTHON set to a path where nothing is)."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from skinsafe.core.bench.browser import chromium
from skinsafe.core.system import MARKER, SKINSAFE, MissingPart, program

NOWHERE = "/nonexistent/skinsafe-test"
CHROMIUM = {"SKINSAFE_CHROMIUM": NOWHERE + "/chromium"}
FRANKY = {"SKINSAFE_FRANKY_PYTHON": NOWHERE + "/python"}

COMMANDS = [  # (argv, env that hides the part, what the line names, how it says to get it)
    (["bench", "runtime", "--view", "browser", "--taxels", "512", "--repeats", "1"], CHROMIUM, "chromium",
     "apt-get install -y chromium"),
    (["bench", "runtime", "--view", "off", "page", "alternating-pinned", "--taxels", "512"], CHROMIUM,
     "chromium for bench runtime --view alternating-pinned", "apt-get install -y chromium"),
    (["bench", "viewers", "--taxels", "512"], CHROMIUM, "chromium for bench viewers", "apt-get install -y chromium"),
    (["bench", "runtime", "--robot", "fr3", "--maps", "skin.json"], FRANKY,
     f"franky-sim's environment ({FRANKY['SKINSAFE_FRANKY_PYTHON']})", "make franky-sim"),
]


@pytest.mark.parametrize("argv,hide,part,how", COMMANDS, ids=[" ".join(c[0][:3]) for c in COMMANDS])
def test_a_command_missing_a_part_exits_2_with_one_line_naming_it(tmp_path, argv, hide, part, how):
    p = subprocess.run([SKINSAFE, *argv], cwd=tmp_path, env={**os.environ, **hide}, capture_output=True, text=True,
                       timeout=300)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr + p.stdout, p.stderr
    assert f"{MARKER}: {part}" in lines[0] and how in lines[0], lines[0]
    assert not p.stdout and not list(tmp_path.iterdir())  # nothing ran, nothing written


def test_a_chromium_named_by_the_variable_is_used_only_where_it_runs(monkeypatch, tmp_path):
    monkeypatch.setenv("SKINSAFE_CHROMIUM", sys.executable)  # an executable file: taken as it is
    assert chromium() == sys.executable
    (tmp_path / "chromium").write_text("#!/bin/sh\n")  # not executable
    for where in (tmp_path / "chromium", tmp_path / "none", tmp_path):
        monkeypatch.setenv("SKINSAFE_CHROMIUM", str(where))
        assert chromium() is None


def test_a_program_missing_from_path_names_its_package(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(MissingPart) as e:
        program("taskset", "util-linux")
    assert str(e.value) == f"{MARKER}: the program `taskset`; install it: `apt-get install -y util-linux`"
    assert isinstance(e.value, FileNotFoundError)  # the CLI's one-line error for a file not found, exit 2
    (tmp_path / "taskset").write_text("#!/bin/sh\n")
    (tmp_path / "taskset").chmod(0o755)
    assert program("taskset", "util-linux") == str(Path(tmp_path) / "taskset")
