"""The README's code blocks, run the way a newcomer would run them.

A fence's first word is its language; GitHub shows it and ignores the rest of the line, which
tells this test what to do with the block:

- ``bash`` / ``sh``: run, in document order, each by ``bash -eu -o pipefail`` in one fresh
  temporary directory, with this interpreter's ``bin`` directory first on ``PATH``, no
  ``CAPEVO_*`` variable inherited, and ``PORT`` set to a free loopback port. A block that serves
  a registry in the background stops it itself; whatever is left of its process group is killed
  after it.
- ``python``: run with this interpreter in that directory, in document order with the shell
  blocks.
- ``python file=NAME`` / ``yaml file=NAME``: a file the other blocks use, written into that
  directory before anything runs.
- ``text``: shown, not run (pictures, synopses). ``text output``: every line of it must appear
  in what the run block just before it printed.
- ``yaml``, ``json``, ``mermaid``: shown, not run.

Any other language, or none, fails :func:`test_every_block_says_what_it_is`, so a new block must
choose.

Invariants:
1. Every run block exits 0, and every ``text output`` line is in its run block's output.
2. Every relative link and every ``scripts/NAME`` the README names exists.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from capevo.runtime.ecm.code import CodeSkill

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
RUN = {"bash", "sh", "python"}
SHOWN = {"text", "yaml", "json", "mermaid"}
FENCE = re.compile(r"^\s*(`{3,}|~{3,})\s*(.*)$")
# Seconds one block may take: the quick start's `capevo evolve --preset tiny` is the longest.
BLOCK_TIMEOUT = 480.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Block:
    """One fenced code block of a Markdown file."""

    line: int
    language: str
    flags: frozenset[str] = frozenset()
    attrs: dict[str, str] = field(default_factory=dict)
    text: str

    @property
    def file(self) -> str | None:
        return self.attrs.get("file")

    @property
    def runs(self) -> bool:
        return self.language in RUN and self.file is None

    def where(self) -> str:
        return f"README.md:{self.line} ({self.language})"


def parse_blocks(markdown: str) -> list[Block]:
    """Every fenced block of ``markdown``, in order.

    Raises:
        AssertionError: a fence is never closed.
    """
    blocks: list[Block] = []
    lines = markdown.splitlines()
    i = 0
    while i < len(lines):
        opened = FENCE.match(lines[i])
        if opened is None:
            i += 1
            continue
        marker, info = opened.groups()
        words = info.split()
        start, body = i + 1, []
        i += 1
        while i < len(lines):
            closed = FENCE.match(lines[i])
            if closed is not None and closed.group(1).startswith(marker) and not closed.group(2).strip():
                break
            body.append(lines[i])
            i += 1
        else:
            raise AssertionError(f"README.md:{start}: fence never closed")
        i += 1
        extra = words[1:]
        blocks.append(
            Block(
                line=start,
                language=words[0] if words else "",
                flags=frozenset(w for w in extra if "=" not in w),
                attrs=dict(w.split("=", 1) for w in extra if "=" in w),
                text="\n".join(body) + "\n",
            )
        )
    return blocks


def readme_blocks() -> list[Block]:
    return parse_blocks(README.read_text(encoding="utf-8"))


def block_env(port: int) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAPEVO_")}
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["PORT"] = str(port)
    env["PYTHONUNBUFFERED"] = "1"
    env["COLUMNS"] = "120"
    return env


def run_block(block: Block, cwd: Path, env: dict[str, str], log: Path) -> str:
    """Run one block in its own process group; return what it printed (stdout and stderr).

    The output goes to ``log``, not a pipe: a background process the block leaves behind would
    hold a pipe open after the block exits.

    Raises:
        AssertionError: it exited non-zero or overran :data:`BLOCK_TIMEOUT`.
    """
    if block.language == "python":
        argv = [sys.executable, "-c", block.text]
    else:
        argv = ["bash", "-eu", "-o", "pipefail", "-c", block.text]
    with log.open("w") as out:
        proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        returncode: int | str = proc.wait(timeout=BLOCK_TIMEOUT)
    except subprocess.TimeoutExpired:
        returncode = f"nothing: it ran over {BLOCK_TIMEOUT:g}s"
    finally:
        # Whatever the block left running (a server it failed to stop) ends with it.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    printed = log.read_text(errors="replace")
    assert returncode == 0, f"{block.where()} exited {returncode}:\n{block.text}\n--- output ---\n{printed}"
    return printed


def test_every_block_says_what_it_is() -> None:
    blocks = readme_blocks()
    assert any(b.runs for b in blocks), "the README runs nothing"
    files = [b.file for b in blocks if b.file is not None]
    assert len(files) == len(set(files)), f"a file is written twice: {files}"
    previous: Block | None = None
    for block in blocks:
        assert block.language in RUN | SHOWN, f"{block.where()}: fence language must be one of {sorted(RUN | SHOWN)}"
        if block.file is not None:
            assert block.language in {"python", "yaml"}, f"{block.where()}: only python and yaml blocks are files"
            assert "/" not in block.file and block.file not in {".", ".."}, f"{block.where()}: file={block.file}"
        if "output" in block.flags:
            assert block.language == "text", f"{block.where()}: only text blocks are output"
            assert previous is not None and previous.runs, f"{block.where()}: output of no run block"
        if block.runs or "output" in block.flags:
            previous = block


def test_what_the_readme_names_exists() -> None:
    text = README.read_text(encoding="utf-8")
    for script in sorted(set(re.findall(r"\bscripts/[\w-]+", text))):
        path = REPO / script
        assert path.is_file() and os.access(path, os.X_OK), f"README names {script}, which is not an executable file"
    for target in sorted(set(re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text))):
        assert (REPO / target).exists(), f"README links to {target}, which does not exist"


def test_the_readme_code_ecm_meets_the_code_contract() -> None:
    """The ECM the quick start publishes loads as a code skill and acts on its interface inputs."""
    (source,) = [b.text for b in readme_blocks() if b.file == "reach.py"]
    skill = CodeSkill(source, filename="reach.py")
    obs = {"robot0_eef_pos": np.zeros(3, np.float32), "Can_pos": np.array([0.0, 0.0, 0.8], np.float32)}
    action = skill.act(obs)
    assert action.shape == (7,) and np.all(np.abs(action) <= 1.0)
    assert not skill.done(obs)


@pytest.mark.slow
@pytest.mark.zenoh
def test_the_readme_runs(tmp_path: Path, free_port: int) -> None:
    blocks = readme_blocks()
    env = block_env(free_port)
    work = tmp_path / "work"
    work.mkdir()
    for block in blocks:
        if block.file is not None:
            (work / block.file).write_text(block.text, encoding="utf-8")
    out = ""
    for block in blocks:
        if block.runs:
            out = run_block(block, work, env, tmp_path / f"block-{block.line}.log")
        elif "output" in block.flags:
            missing = [ln for ln in block.text.splitlines() if ln.strip() and ln.strip() not in out]
            assert not missing, f"{block.where()}: not printed: {missing}\n--- output ---\n{out}"
