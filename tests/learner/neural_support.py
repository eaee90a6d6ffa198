"""Shared pieces of the neural learner tests (imported as ``neural_support``).

* :func:`write_scripted_trace`: real T1 episodes driven by the scripted pick reference, written
  to a real MCAP trace as the runtime would (flat task observations, each step attributed to the
  decomposition step that was running, one ``/episode/summary`` per episode);
* :func:`start_registry` / :func:`start_learner`: the registry server and learner workers as
  real processes on loopback (multicast scouting off: the registry's configs keep it off).
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from procs import LOOPBACK, wait_ready

from capevo.records import CapabilitySet
from capevo.registry.predicates import predicate_holds
from capevo.runtime.ecm.marshal import flatten_inputs, marshal_inputs
from capevo.runtime.tasks import Perturbations, make_task, task_spec
from capevo.runtime.tasks.scripted import REFERENCES
from capevo.runtime.traces import EnvStep, EpisodeSummary, TraceMetadata, TraceWriter

REPO = Path(__file__).resolve().parents[2]


def subprocess_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAPEVO_")}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


# --- traces from scripted episodes -----------------------------------------------------------


@dataclass
class TracedEpisode:
    seed: int
    success: bool
    steps: int
    ecm_obs: dict[str, list[np.ndarray]] = field(default_factory=dict)
    """Per ECM, its interface observation at each of its steps (for checking exports)."""
    ecm_actions: dict[str, list[np.ndarray]] = field(default_factory=dict)


def write_scripted_trace(
    path: Path,
    *,
    seeds: list[int],
    horizons: list[int],
    versions: dict[str, int],
    inputs: dict[str, Any],
    run_id: str | None = None,
    acting: str | None = None,
) -> list[TracedEpisode]:
    """Run scripted T1 episodes (one per seed, cut at its horizon) and trace them to ``path``.

    Steps are attributed to the decomposition step running, advancing when a step's
    termination predicate holds (as the runtime's plan does on a successful path).
    ``inputs`` maps ECM names to their interface inputs, to record the expected ECM observations.
    ``acting`` attributes every step to that ECM instead: one ECM that never hands over and does
    the whole task itself.
    """
    spec = task_spec("T1")
    env = make_task("T1", perturbations=Perturbations.none(), horizon=max(horizons))
    meta = TraceMetadata.collect(
        run_id=run_id or f"scripted-{uuid.uuid4().hex[:8]}",
        task=spec.name,
        capability_set=CapabilitySet(revision=1, active=dict(versions)),
        phi_hash="f" * 64,
        agent_identity_hash="a" * 64,
        seeds=seeds,
    )
    out: list[TracedEpisode] = []
    try:
        with TraceWriter(path, meta) as writer:
            for episode, (seed, horizon) in enumerate(zip(seeds, horizons, strict=True)):
                obs, info = env.reset(seed=seed)
                stage = 0
                record = TracedEpisode(seed=seed, success=False, steps=0)
                total = 0.0
                for t in range(horizon):
                    while stage < len(spec.decomposition) - 1 and predicate_holds(
                        spec.decomposition[stage].termination, env.signals()
                    ):
                        stage += 1
                    ecm = acting or spec.decomposition[stage].ecm
                    if ecm in inputs:
                        record.ecm_obs.setdefault(ecm, []).append(
                            flatten_inputs(marshal_inputs(env.obs_dict, inputs[ecm]), inputs[ecm])
                        )
                    action = REFERENCES["pick"](env.obs_dict)
                    record.ecm_actions.setdefault(ecm, []).append(np.asarray(action, np.float32))
                    next_obs, reward, terminated, truncated, info = env.step(action)
                    total += reward
                    writer.write_env_step(
                        EnvStep(
                            episode=episode,
                            step=t,
                            ecm=ecm,
                            version=versions.get(ecm, 0),
                            obs=tuple(obs.tolist()),
                            action=tuple(float(a) for a in action),
                            reward=float(reward),
                            next_obs=tuple(next_obs.tolist()),
                            terminated=terminated,
                            truncated=truncated or (t == horizon - 1 and not terminated),
                            is_success=bool(info["is_success"]),
                        )
                    )
                    obs = next_obs
                    record.steps = t + 1
                    if terminated:
                        break
                record.success = bool(info["is_success"])
                writer.write_episode_summary(
                    EpisodeSummary(
                        episode=episode,
                        seed=seed,
                        success=record.success,
                        total_reward=total,
                        steps=record.steps,
                        interventions=0,
                        unsafe_steps=0,
                        capability_set=dict(versions),
                        duration_s=0.1,
                    )
                )
                out.append(record)
    finally:
        env.close()
    return out


# --- processes -----------------------------------------------------------------------------


@dataclass
class Proc:
    proc: subprocess.Popen[str]
    log_path: Path

    def stop(self, timeout: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return int(self.proc.returncode)

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


def start_registry(root: Path, port: int, *, timeout: float = 60.0) -> Proc:
    """``python -m capevo.registry.service`` on ``tcp/127.0.0.1:port``; waits for its READY line."""
    root.mkdir(parents=True, exist_ok=True)
    log_path = root.parent / f"{root.name}-registry.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "capevo.registry.service",
                "--root",
                str(root),
                "--listen",
                f"tcp/{LOOPBACK}:{port}",
            ],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=subprocess_env(),
            cwd=REPO,
        )
    if wait_ready(proc, timeout) is not None:
        return Proc(proc=proc, log_path=log_path)
    proc.kill()
    proc.wait()
    raise RuntimeError(f"registry did not start:\n{log_path.read_text(errors='replace')}")


def learner_args(endpoint: str, *extra: Any) -> list[str]:
    return [sys.executable, "-m", "capevo.cli.learner", "serve", "--connect", endpoint, "--json", *map(str, extra)]


def start_learner(endpoint: str, log_path: Path, *extra: Any) -> Proc:
    """A learner worker process; stdout is a pipe of JSON event lines, stderr goes to ``log_path``."""
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            learner_args(endpoint, *extra),
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=subprocess_env(),
            cwd=REPO,
        )
    return Proc(proc=proc, log_path=log_path)


def read_events(proc: Proc, until: str, *, timeout: float) -> list[dict[str, Any]]:
    """JSON events from ``proc``'s stdout up to and including the first ``until`` event."""
    assert proc.proc.stdout is not None
    events: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.proc.stdout], [], [], 0.2)
        if ready:
            line = proc.proc.stdout.readline()
            if not line:
                break
            events.append(json.loads(line))
            if events[-1].get("event") == until:
                return events
        elif proc.proc.poll() is not None:
            break
    raise AssertionError(f"no {until!r} event; got {events}\n--- stderr ---\n{proc.log_text()[-4000:]}")
