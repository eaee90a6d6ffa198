"""Shared pieces of the runtime tests: code skills for T1 pick, publishing them, processes.

The skills are real code ECMs (the module contract of :mod:`capevo.runtime.ecm.code`),
published into a real registry with the descriptors of T1's decomposition.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from procs import kill, terminate

from capevo.errors import Invalid
from capevo.records import EcmVersion, Interface, IOSpec, Kind, Origin, PublishSpec
from capevo.registry.api import Registry
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.tasks import task_spec

PICK = task_spec("T1")

ACTION = (IOSpec(name="action", shape=(7,), low=-1.0, high=1.0),)
EEF = IOSpec(name="robot0_eef_pos", shape=(3,), units="m")
CAN = IOSpec(name="Can_pos", shape=(3,), units="m")

# hover 9 cm, not 6: at 6 cm the right finger clipped the can's top while crossing to a far can
# (28-41 N by the safety monitor on T1 gate seeds 100001 and 100006), so the gate refused this
# reach against one that never reaches the can (issue 18: more unsafe episodes).
REACH = '''
"""Bring the open gripper onto the can: hover above it, then descend."""
import numpy as np

PARAMS = {"gain": 10.0, "hover": 0.09, "xy_tol": 0.03, "dig": 0.015}


def act(obs, params):
    eef = obs["robot0_eef_pos"]
    can = obs["Can_pos"]
    err = can - eef
    err[2] -= params["dig"]
    if float(np.hypot(err[0], err[1])) > params["xy_tol"]:
        err = np.array([err[0], err[1], can[2] + params["hover"] - eef[2]])
    m = np.clip(err * params["gain"], -1.0, 1.0)
    return [float(m[0]), float(m[1]), float(m[2]), 0.0, 0.0, 0.0, -1.0]
'''

GRASP = '''
"""Close the gripper where it is."""
PARAMS = {}


def act(obs, params):
    return [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
'''

LIFT = '''
"""Lift straight up with the gripper closed."""
PARAMS = {"speed": 1.0}


def act(obs, params):
    return [0.0, 0.0, params["speed"], 0.0, 0.0, 0.0, 1.0]
'''

# A reach whose own done() ends it at once: lets tests see done() end an ECM.
REACH_DONE_AT_ONCE = """
def act(obs, params):
    return [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]


def done(obs, params):
    return True
"""

RAISES = """
def act(obs, params):
    raise ValueError("deliberate failure in act")
"""

NAN = """
def act(obs, params):
    return [float("nan")] * 7
"""

BAD_SHAPE = """
def act(obs, params):
    return [0.0, 0.0, 0.0]
"""

HANGS = """
def act(obs, params):
    x = 0
    while True:
        x = x + 1
"""

# Adversarial: straight up, full speed, far past the workspace box's +z face (1.3 m).
OUT_OF_BOX = """
def act(obs, params):
    return [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]
"""

SOURCES: Mapping[str, str] = {"pick.reach": REACH, "pick.grasp": GRASP, "pick.lift": LIFT}
INPUTS: Mapping[str, tuple[IOSpec, ...]] = {
    "pick.reach": (EEF, CAN),
    "pick.grasp": (EEF, CAN),
    "pick.lift": (EEF,),
}


def step_of(name: str) -> Any:
    return next(s for s in PICK.decomposition if s.ecm == name)


def skill_spec(
    name: str, *, origin: Origin = Origin.MANUAL, inputs: tuple[IOSpec, ...] | None = None, parent: int | None = None
) -> PublishSpec:
    """The publish spec of a T1 skill: the task's descriptor for ``name`` and a 7-dim action."""
    return PublishSpec(
        kind=Kind.CODE,
        descriptor=step_of(name).descriptor(),
        interface=Interface(inputs=INPUTS[name] if inputs is None else inputs, outputs=ACTION),
        origin=origin,
        parent=parent,
    )


def publish(
    registry: Registry,
    name: str,
    source: str,
    *,
    origin: Origin = Origin.MANUAL,
    promote: bool = True,
    inputs: tuple[IOSpec, ...] | None = None,
) -> EcmVersion:
    """Publish ``source`` as the next version of ``name`` (and promote it)."""
    record = registry.publish(name, source.encode(), skill_spec(name, origin=origin, inputs=inputs))
    if promote:
        record = registry.promote(name, record.version, reason="test")
    return record


def publish_pick(registry: Registry, *, origin: Origin = Origin.MANUAL, **overrides: str) -> dict[str, EcmVersion]:
    """Publish and promote reach, grasp and lift (``overrides`` replaces sources by short name)."""
    out = {}
    for name, source in SOURCES.items():
        short = name.split(".", 1)[1]
        out[name] = publish(registry, name, overrides.get(short, source), origin=origin)
    return out


def chunk_compressions(path: str | os.PathLike[str]) -> set[str]:
    """The compression strings of an MCAP file's chunks, from its summary ("" is none)."""
    with Path(path).open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None, f"{path} has no summary"
    return {c.compression for c in summary.chunk_indexes}


# --- processes -------------------------------------------------------------------------


@dataclass
class Proc:
    """A child process whose stdout carries JSON lines (``READY {...}`` or ``{...}``)."""

    popen: subprocess.Popen[str]
    log_path: Path
    lines: list[dict[str, Any]] = field(default_factory=list)

    def read_until(self, predicate: Any, timeout: float) -> dict[str, Any]:
        """Read stdout lines until one satisfies ``predicate``; return it (or raise with the log)."""
        deadline = time.monotonic() + timeout
        for line in self.lines:
            if predicate(line):
                return line
        assert self.popen.stdout is not None
        while time.monotonic() < deadline and not self.popen.stdout.closed:
            ready, _, _ = select.select([self.popen.stdout], [], [], 0.2)
            if ready:
                if self.popen.stdout.closed:
                    break
                text = self.popen.stdout.readline()
                if not text:
                    break
                line = _parse(text)
                if line is None:
                    continue
                self.lines.append(line)
                if predicate(line):
                    return line
            elif self.popen.poll() is not None:
                break
        raise AssertionError(
            f"no matching line within {timeout}s (exit {self.popen.poll()}); lines: {self.lines[-5:]}\n"
            f"log:\n{self.log()[-4000:]}"
        )

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def running(self) -> bool:
        return self.popen.poll() is None

    def terminate(self, timeout: float = 30.0) -> int:
        code = terminate(self.popen, timeout)
        self._drain()
        return code

    def _drain(self) -> None:
        """Keep whatever the exited process still had on stdout, then close it."""
        if self.popen.stdout is None or self.popen.stdout.closed:
            return
        for text in self.popen.stdout.read().splitlines():
            line = _parse(text)
            if line is not None:
                self.lines.append(line)
        self.popen.stdout.close()

    def kill(self) -> None:
        kill(self.popen)
        self._drain()


def _parse(text: str) -> dict[str, Any] | None:
    text = text.strip()
    if text.startswith("READY "):
        text = text[len("READY ") :]
        try:
            return {"event": "ready", **json.loads(text)}
        except ValueError:
            return None
    try:
        value = json.loads(text)
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def spawn(cmd: list[str], log_path: Path, env: Mapping[str, str] | None = None) -> Proc:
    with open(log_path, "a") as log_file:
        popen = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=log_file, text=True, env={**os.environ, **(env or {})}
        )
    return Proc(popen=popen, log_path=log_path)


def start_worker(
    connect: str,
    *,
    task: str,
    log_path: Path,
    extra: list[str] | None = None,
    namespace: str = "capevo",
    timeout: float = 90.0,
) -> Proc:
    """``python -m capevo.cli.runtime serve --json ...`` once it reports ``ready``."""
    proc = spawn(
        [
            sys.executable,
            "-m",
            "capevo.cli.runtime",
            "serve",
            "--connect",
            connect,
            "--task",
            task,
            "--namespace",
            namespace,
            "--json",
            *(extra or []),
        ],
        log_path,
    )
    proc.read_until(lambda line: line.get("event") == "ready", timeout)
    return proc


Behaviour = Callable[[int], tuple[bool, float, int] | tuple[bool, float, int, int]]
"""``seed -> (success, reward, steps[, unsafe_steps])`` of one version in :class:`FakeEvaluator`."""


class FakeEvaluator:
    """In-memory :class:`~capevo.runtime.evaluation.Evaluator` for tests of the gate's and the
    monitor's decisions (their statistics and records, against a real registry on disk).

    A fake: no simulator runs. Each ``(ECM name, version)`` has a deterministic behaviour
    ``seed -> (success, reward, steps)``; ``evaluate`` looks up the single pinned version and
    returns one outcome per seed with ``capability_set`` = ``versions`` (and ``unsafe_steps``
    when the behaviour gives a fourth value).

    Args:
        behaviours: ``{(name, version): behaviour}``.
    """

    def __init__(self, behaviours: Mapping[tuple[str, int], Behaviour] | None = None) -> None:
        self.behaviours: dict[tuple[str, int], Behaviour] = dict(behaviours or {})
        self.calls: list[tuple[str, dict[str, int], tuple[int, ...]]] = []

    def set(self, name: str, version: int, behaviour: Behaviour) -> None:
        self.behaviours[(name, version)] = behaviour

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        """One outcome per seed from the pinned version's behaviour.

        Raises:
            Invalid: not exactly one pinned version, or no behaviour for it.
        """
        if len(versions) != 1:
            raise Invalid(f"FakeEvaluator pins exactly one ECM, got {dict(versions)}", details={"field": "versions"})
        ((name, version),) = versions.items()
        behaviour = self.behaviours.get((name, version))
        if behaviour is None:
            raise Invalid(f"FakeEvaluator has no behaviour for {name} v{version}", details={"field": "versions"})
        self.calls.append((task, dict(versions), tuple(seeds)))
        out = []
        for s in seeds:
            success, reward, steps, *unsafe = behaviour(int(s))
            out.append(
                EpisodeOutcome(
                    seed=int(s),
                    success=bool(success),
                    reward=float(reward),
                    steps=int(steps),
                    duration_s=float(steps) * 0.01,
                    interventions=0,
                    unsafe_steps=int(unsafe[0]) if unsafe else 0,
                    ecm_failures=0,
                    capability_set=dict(versions),
                )
            )
        return out
