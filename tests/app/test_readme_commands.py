"""Every shell command the README and the docs show runs as written on a fresh clone.

Each ```bash block of README.md and of the docs pages (in mkdocs.yml's nav order, blocks in page order:
a later block may use what an earlier one made) runs as one bash script (`set -euo pipefail`) in
a copy of the checkout's files (tracked, or untracked and not ignored: what a fresh clone holds),
with this environment's `skinsafe` on PATH and its .venv linked in for `make`. A new ```bash block
is picked up by itself. A command too slow for the suite declares, in an HTML comment anywhere in
the README or a docs page (a line of its own, invisible when rendered), flags appended to it (its reduced size), or that it is not
run and why:

    <!-- readme-test: skinsafe experiment maze += --quick --out out/mq -->
    <!-- readme-test: make test => skip: the suite this check is part of -->
    <!-- readme-test: skinsafe replay poke.mcap => skip: runs as README.md `skinsafe replay out/tour/poke` -->

A skip that another block's command covers names that block by its page and a part of that command
that no other block of the page holds.

The command is matched as written in its block (comments dropped, spaces collapsed). A directive
naming no command of a bash block fails, as does any command that fails, but for one that lacks a part of the
machine (a browser, franky-sim's environment): it exits 2 with one line holding `missing system part: PART; HOW`
(core/system.py), and its block is skipped with that line as the reason (the commands before it ran). Blocks of
other languages (```python, ```json, plain ``` for synopses and output) are not run."""
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from skinsafe.core.app.readme import pages
from skinsafe.core.system import MARKER

ROOT = Path(__file__).resolve().parents[2]
PAGES = pages(ROOT)
DIRECTIVE = re.compile(r"^<!--\s*readme-test:\s*(.+?)\s*(\+=|=>)\s*(.+?)\s*-->", re.M)


def _strip_comment(line: str) -> str:
    """The line without its trailing `# comment` (a # at the start or after a space, outside quotes)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


def _norm(cmd: str) -> str:
    return " ".join(cmd.split())


def bash_blocks(text: str) -> list[tuple[int, list[str]]]:
    """(line number, commands) of every ```bash block; continuation lines joined, comments dropped."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        if lines[i].strip() == "```bash":
            start, cmds, pending = i + 1, [], ""
            i += 1
            while lines[i].strip() != "```":
                line = pending + _strip_comment(lines[i])
                pending = line[:-1] + " " if line.endswith("\\") else ""
                if not pending and line.strip():
                    cmds.append(_norm(line))
                i += 1
            blocks.append((start, cmds))
        i += 1
    return blocks


def directives(text: str) -> dict[str, tuple[str, str]]:
    """command -> ("+=", flags appended) or ("=>", "skip: reason")."""
    found = {}
    for cmd, op, what in DIRECTIVE.findall(text):
        assert _norm(cmd) not in found, f"docs: two readme-test directives for '{cmd}'"
        assert op == "+=" or what.startswith("skip: ") and len(what) > 10, \
            f"README: readme-test '{cmd} {op} {what}': use '+= FLAGS' or '=> skip: REASON'"
        found[_norm(cmd)] = (op, what)
    return found


TEXTS = {page.relative_to(ROOT).as_posix(): page.read_text() for page in PAGES}
BLOCKS = [(page, line, cmds) for page, text in TEXTS.items() for line, cmds in bash_blocks(text)]
DIRECTIVES = directives("\n".join(TEXTS.values()))


def test_every_directive_names_a_command_of_a_bash_block():
    commands = {c for _, _, cmds in BLOCKS for c in cmds}
    assert BLOCKS and not set(DIRECTIVES) - commands, f"docs: readme-test directives for no command: " \
                                                      f"{sorted(set(DIRECTIVES) - commands)}"


RUNS_AS = re.compile(r"runs as (\S+\.md) `([^`]+)`")


def test_a_skipped_command_names_the_block_that_runs_its_path():
    """`=> skip: runs as PAGE `TEXT`` names the one block of PAGE with a command holding TEXT (not a line number:
    edits above the block would move it)."""
    named = [m for _, what in DIRECTIVES.values() for m in RUNS_AS.findall(what)]
    unnamed = [what for _, what in DIRECTIVES.values() if "runs as" in what and not RUNS_AS.search(what)]
    found = {(page, cmd): sum(any(_norm(cmd) in c for c in cmds) for p, _, cmds in BLOCKS if p == page)
             for page, cmd in named}
    assert named and not unnamed, f"docs: readme-test 'runs as' without PAGE `COMMAND`: {unnamed}"
    assert all(n == 1 for n in found.values()), \
        f"docs: readme-test 'runs as' names no block or several: {[k for k, n in found.items() if n != 1]}"


def test_parsing_keeps_quotes_and_joins_continuations():
    blocks = bash_blocks("```bash\na 'x # y' # note\nb \\\n   --c 1  # more\n# only a comment\n```\n")
    assert blocks == [(1, ["a 'x # y'", "b --c 1"])]
    assert directives("<!-- readme-test: a  'x # y' += --quick -->") == {"a 'x # y'": ("+=", "--quick")}


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    """The checkout's files as a fresh clone has them, with this environment's .venv linked in."""
    dst = tmp_path_factory.mktemp("readme") / "skinsafe"
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, check=True).stdout.decode().split("\0")
    for f in filter(None, files):
        if (ROOT / f).is_file():
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, dst / f)
    (dst / ".venv").symlink_to(Path(sys.prefix))
    if (ROOT / ".venv-franky").is_dir():  # franky-sim's environment, which `make test` builds before the suite
        (dst / ".venv-franky").symlink_to(ROOT / ".venv-franky")
    for f in ("pyproject.toml", "Makefile"):  # older than the venvs' stamps: `make` never reinstalls into them
        os.utime(dst / f, (0, 0))
    return dst


FAILED = "readme-test: failed: "
LOOP = re.compile(r"\bskinsafe (run|bench runtime)\b")  # commands that start `skinsafe run` (the real-time slot)


def missing_part(out: str, returncode: int) -> str | None:
    """The failing command's `missing system part` line, when it ended so (exit 2, that line its last before the
    failure): a part of the machine it needs is not here."""
    lines = out.splitlines()
    at = max((i for i, x in enumerate(lines) if x.startswith(FAILED)), default=None)
    if returncode != 2 or not at or f"{MARKER}: " not in lines[at - 1]:
        return None
    return f"`{lines[at][len(FAILED):]}`: {lines[at - 1]}"


def test_a_command_missing_a_part_skips_its_block_and_any_other_failure_fails():
    out = "$ a\nskinsafe bench runtime: error: missing system part: chromium; install it\nreadme-test: failed: a --x\n"
    assert missing_part(out, 2) == "`a --x`: skinsafe bench runtime: error: missing system part: chromium; install it"
    assert missing_part(out, 1) is None and missing_part(out.replace("missing system part", "bad"), 2) is None
    assert missing_part("missing system part: x\n", 2) is None  # no failed command


def _script(cmds: list[str], slot: Path) -> str:
    """The block as one bash script; a command that runs the control loop holds the machine's real-time slot (`slot`,
    conftest.realtime_lock: flock on that file) while it runs, its neighbours not."""
    lines = ["set -euo pipefail", f"trap 'echo \"{FAILED}$BASH_COMMAND\" >&2' ERR"]
    for c in cmds:
        op, what = DIRECTIVES.get(c, ("", ""))
        if op == "=>":
            lines.append(f"echo {shlex.quote('readme-test: not run: ' + c + ' (' + what + ')')}")
            continue
        run = f"{c} {what}" if op == "+=" else c
        lines.append(f"echo {shlex.quote('$ ' + run)} >&2")
        if LOOP.search(c):
            assert not c.endswith("&"), f"docs: `{c}`: the control loop in the background would run without its slot"
            run = f"{{ flock 9; {run}; }} 9>>{shlex.quote(str(slot))}"
        lines.append(run)
    return "\n".join(lines) + "\n"


def test_only_the_loop_holds_the_real_time_slot(tmp_path):
    """The slot is held while the loop's command runs (flock, the lock conftest.realtime_slot takes) and given back
    after it: the block's next command runs while another process takes the slot."""
    import fcntl

    slot, between = tmp_path / "realtime.lock", tmp_path / "between"
    script = _script([f"echo skinsafe run; if flock -n {slot} true; then exit 7; fi", f"touch {between} && sleep 5"], slot)
    assert script.count("flock 9") == 1
    proc = subprocess.Popen(["bash", "-c", script], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        while not between.exists():
            assert proc.poll() is None, f"the slot was free while the loop's command ran: {proc.stderr.read()}"
            time.sleep(0.05)
        with open(slot, "a") as f:  # taken here while the block's next command runs
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    finally:
        proc.kill()
        proc.wait()


def block_group(page: str) -> str:
    """The pytest-xdist group of a page's blocks: one worker runs a group's blocks in order (a block may use an
    earlier one's files); the groups never use each other's files (the simulate pages make the map the deploy page
    deploys, the run page the map the live view shows), so two workers can run two groups at once. A command that
    runs the control loop waits for the machine's real-time slot (`_script`), the block's other commands (designs,
    replays, views) run beside the `realtime` group's tests."""
    parts = page.split("/")
    if len(parts) < 3:
        return "docs-" + parts[-1].removesuffix(".md").lower()
    return "docs-" + {"deploy": "simulate"}.get(parts[1], parts[1])


@pytest.mark.parametrize("page,line,cmds", [pytest.param(p, n, c, marks=pytest.mark.xdist_group(block_group(p)))
                                             for p, n, c in BLOCKS],
                         ids=[f"{p}:{n}-{c[0].split(' #')[0][:40]}" if c else f"{p}:{n}" for p, n, c in BLOCKS])
def test_docs_bash_block_runs_as_written(clone, page, line, cmds, tmp_path, realtime_lock):
    env = {**os.environ, "PATH": f"{Path(sys.prefix) / 'bin'}{os.pathsep}{os.environ['PATH']}", "MPLBACKEND": "Agg"}
    log = tmp_path / "out.txt"
    t = time.perf_counter()
    with open(log, "w") as f:  # a file, not a pipe: a command left running in the background cannot hold it open
        proc = subprocess.Popen(["bash", "-c", _script(cmds, realtime_lock)], cwd=clone, env=env, stdout=f, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            proc.wait(timeout=600)
        finally:
            try:  # whatever the block left running (an emulator started with &) ends with it
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    missing = missing_part(log.read_text(), proc.returncode)
    if missing:
        pytest.skip(f"{page} line {line}: {missing}")
    assert proc.returncode == 0, f"{page} line {line}: the block failed after {time.perf_counter() - t:.0f} s:\n" \
                                 f"{log.read_text()[-4000:]}"
