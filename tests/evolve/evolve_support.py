"""Shared pieces of the evolve tests.

Fakes (no simulator) of the loop's narrow dependencies, for the fast loop tests:

* :class:`ScriptedEvaluator`: an :class:`~capevo.runtime.evaluation.Evaluator` whose episodes'
  success is a function of (versions run, seed); it resolves unpinned ECMs to the registry's
  active versions like the real one does.
* :class:`ParamUpdater`: an updater that proposes the active code skill with one parameter
  changed (a real code artifact, published for real).
* :class:`ChainUpdater`: a :class:`ParamUpdater` that accepts companions (so the loop chains
  updates) and returns, as the candidate's training experience, real MCAP traces of episodes
  whose plans say which step they stalled in.

Everything else in these tests is real: the on-disk registry, the gate and its statistics,
the degradation monitor, the persistent agent and its episodic memory, the metrics files.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from capevo.agent import DecompositionPolicy, EpisodicMemory, IdentityMemory, PersistentAgent
from capevo.evolve.config import CemSettings, EvolveConfig
from capevo.evolve.learners import Proposal, UpdateRequest
from capevo.evolve.loop import EvolutionLoop, ensure_v0
from capevo.evolve.progress import ProgressSink, RecordingProgress
from capevo.evolve.state import RunManifest
from capevo.learner.base import Candidate
from capevo.records import CapabilitySet, Origin, Provenance, PublishSpec
from capevo.registry.local import LocalRegistry
from capevo.runtime.ecm.code import read_params, with_params
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate import GateConfig, SeedPlan
from capevo.runtime.monitor import MonitorConfig
from capevo.runtime.tasks import task_spec
from capevo.runtime.traces import EcmInvocation, EpisodeSummary, PlanStep, TraceMetadata, TraceWriter
from capevo.runtime.traces import Outcome as CallOutcome
from capevo.runtime.traces.records import Intervention, UnsafeStep

TASK = "pick"
NAMES = task_spec(TASK).ecm_names
PLAN = SeedPlan(base_seed=0)

Behaviour = Callable[[Mapping[str, int], int], bool]
"""``(versions run, seed) -> success``."""


class Crash(BaseException):
    """Stands in for the process dying at a chosen point (not an Exception: nothing catches it)."""


class ScriptedEvaluator:
    """A fake evaluator: success = ``behaviour(versions, seed)``; reward 1 + success; steps 20 / 40.

    Args:
        registry: Unpinned ECMs run at its active versions.
        behaviour: Decides success.
        crash_on_call: Raise :class:`Crash` at this call (1-based) instead of answering.
    """

    def __init__(self, registry: Any, behaviour: Behaviour, *, crash_on_call: int | None = None) -> None:
        self.registry = registry
        self.behaviour = behaviour
        self.crash_on_call = crash_on_call
        self.calls: list[tuple[dict[str, int], tuple[int, ...]]] = []

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        active = self.registry.capability_set().active
        ran = {n: int(versions.get(n, active[n])) for n in task_spec(task).ecm_names}
        self.calls.append((ran, tuple(seeds)))
        if self.crash_on_call is not None and len(self.calls) == self.crash_on_call:
            raise Crash(f"crash at evaluate call {len(self.calls)}")
        out = []
        for s in seeds:
            ok = bool(self.behaviour(ran, int(s)))
            out.append(
                EpisodeOutcome(
                    seed=int(s),
                    success=ok,
                    reward=1.0 + ok + (s % 7) * 0.01,
                    steps=20 if ok else 40,
                    duration_s=0.01,
                    interventions=0,
                    unsafe_steps=0,
                    ecm_failures=0,
                    capability_set=ran,
                )
            )
        return out


def reach_at_least(version: int) -> Behaviour:
    """Succeed exactly when pick.reach runs at ``version`` or later."""
    return lambda versions, seed: versions["pick.reach"] >= version


class ParamUpdater:
    """Proposes the active version of the requested ECM with ``PARAMS[key]`` scaled.

    Args:
        tamper: Called with the request before proposing (a rogue learner touching the agent).
        fail: Raise this instead of proposing.
    """

    name = "param-fake"

    def __init__(
        self,
        registry: Any,
        *,
        key: str | None = None,
        scale: float = 1.5,
        tamper: Callable[[UpdateRequest], None] | None = None,
        fail: BaseException | None = None,
        same: bool = False,
    ) -> None:
        self.registry = registry
        self.key = key
        self.scale = scale
        self.tamper = tamper
        self.fail = fail
        self.same = same
        self.requests: list[UpdateRequest] = []
        self.closed = False

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        self.requests.append(request)
        if self.tamper is not None:
            self.tamper(request)
        if self.fail is not None:
            raise self.fail
        n = len(self.requests)
        cand = self._scaled(request.ecm, None if self.same else lambda v: v * self.scale * n, key=self.key)
        return Proposal(learner=self.name, candidate=cand, episodes=4)

    def _scaled(self, ecm: str, change: Callable[[float], float] | None, *, key: str | None = None) -> Candidate:
        """A clone of ``ecm``'s active version with ``PARAMS[key]`` (default the first) changed
        (None: the same source)."""
        parent = self.registry.get_version(ecm)
        source = self.registry.get_artifact(ecm, parent.version).decode()
        params = read_params(source)
        key = key or next(iter(params))
        new = source if change is None else with_params(source, {key: change(params[key])})
        spec = PublishSpec(
            kind=parent.kind,
            descriptor=parent.descriptor,
            interface=parent.interface,
            parent=parent.version,
            origin=Origin.CLONE,
            provenance=Provenance(learner_id=self.name, config_hash="0" * 64, traces=()),
        )
        return Candidate(ecm=ecm, artifact=new.encode(), spec=spec)

    def close(self) -> None:
        self.closed = True


def write_trace(
    path: Path, episodes: Sequence[tuple[int, bool, Sequence[str]]], *, unsafe: str | None = None
) -> list[EpisodeOutcome]:
    """A real MCAP trace of ``(seed, success, plan)`` episodes (one invocation per plan entry),
    and their outcomes pointing at it; ``unsafe``: the safety monitor grades every step of that
    ECM unsafe (a contact over 20 N), which governance had tried to stop."""
    meta = TraceMetadata.collect(
        run_id="chain",
        task=TASK,
        capability_set=CapabilitySet(revision=1, active=dict.fromkeys(NAMES, 0)),
        phi_hash="phi",
        agent_identity_hash="agent",
    )
    out = []
    with TraceWriter(path, meta) as w:
        for i, (seed, success, plan) in enumerate(episodes):
            for j, ecm in enumerate(plan):
                w.write_plan_step(PlanStep(episode=i, step=j, ecm=ecm, version=0, reason="next"))
                w.write_invocation(
                    EcmInvocation(
                        episode=i,
                        step=j,
                        ecm=ecm,
                        version=0,
                        input_state=(0.0,),
                        output=None,
                        duration_s=0.001,
                        outcome=CallOutcome.OK,
                    )
                )
                if ecm == unsafe:
                    w.write_unsafe_step(
                        UnsafeStep(episode=i, step=j, broken=("force",), reasons=("arm 0: force: 31 N on bin1",))
                    )
                    w.write_intervention(
                        Intervention(
                            episode=i,
                            step=j,
                            constraint="contact_force",
                            original_action=(0.0,) * 7,
                            result_action=(0.0,) * 7,
                            reason="contact force above 20 N",
                        )
                    )
            if not success:
                w.write_plan_step(PlanStep(episode=i, step=len(plan), ecm="", version=0, reason="stalled"))
            summary = EpisodeSummary(
                episode=i,
                seed=seed,
                success=success,
                total_reward=1.0,
                steps=len(plan),
                interventions=0,
                unsafe_steps=sum(1 for ecm in plan if ecm == unsafe),
                capability_set=dict.fromkeys(NAMES, 0),
                duration_s=0.01,
            )
            w.write_episode_summary(summary)
            out.append(
                EpisodeOutcome(
                    seed=seed,
                    success=success,
                    reward=1.0,
                    steps=len(plan),
                    duration_s=0.01,
                    interventions=0,
                    unsafe_steps=0,
                    ecm_failures=0,
                    capability_set=dict.fromkeys(NAMES, 0),
                    trace_path=str(path),
                )
            )
    return out


class ChainUpdater(ParamUpdater):
    """A :class:`ParamUpdater` the loop may chain: it takes companions and reports experience.

    Args:
        trace_dir: Where the experience traces go.
        stalls: Per learned ECM, the plan its candidate's training episodes stall with (None:
            they all succeed); an ECM not listed succeeds.
        improved: Whether candidates claim to beat their parent on the training seeds (one
            answer for all, or one per call in order).
        unsafe: Per learned ECM, the ECM governance stops in its candidate's episodes.
        steps: The env steps each proposal reports it spent.
        tied: Per learned ECM, the ECMs whose candidates come with its own (``--tie-siblings``):
            each its active source with its first parameter doubled.
    """

    supports_companions = True

    def __init__(
        self,
        registry: Any,
        trace_dir: Path,
        stalls: Mapping[str, Sequence[str] | None],
        *,
        improved: bool | Sequence[bool] = True,
        unsafe: Mapping[str, str] | None = None,
        steps: int = 0,
        tied: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        super().__init__(registry)
        self.tied = dict(tied or {})
        self.unsafe = dict(unsafe or {})
        self.trace_dir = trace_dir
        self.stalls = dict(stalls)
        self.improved = improved
        self.steps = steps

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        from capevo.learner.base import Score

        proposal = super().propose(request, progress)
        assert proposal is not None and proposal.candidate is not None
        plan = self.stalls.get(request.ecm)
        path = self.trace_dir / f"exp-{len(self.requests)}.mcap"
        episodes = [(s, plan is None, plan or list(NAMES)) for s in (1, 2, 3)]
        experience = write_trace(path, episodes, unsafe=self.unsafe.get(request.ecm))
        improved = self.improved if isinstance(self.improved, bool) else self.improved[len(self.requests) - 1]
        good = Score(success_rate=0.0, progress=0.5 if improved else 0.0, reward_per_step=0.0, episodes=3)
        base = Score(success_rate=0.0, progress=0.0, reward_per_step=0.0, episodes=3)
        cand = Candidate(
            ecm=request.ecm,
            artifact=proposal.candidate.artifact,
            spec=proposal.candidate.spec,
            score=good,
            baseline=base,
            tied=tuple(
                dataclasses.replace(
                    self._scaled(name, lambda v: v * 2.0 + len(self.requests)), score=good, baseline=base
                )
                for name in self.tied.get(request.ecm, ())
            ),
        )
        return Proposal(learner=self.name, candidate=cand, episodes=4, steps=self.steps, experience=tuple(experience))


def fake_config(**changes: Any) -> EvolveConfig:
    """Small budgets with a gate that can promote a clear win on 8 paired seeds."""
    base = EvolveConfig(
        preset="test",
        iterations=2,
        live_episodes=3,
        gate_episodes=8,
        gate=GateConfig(min_n=8, alpha=0.05, delta=0.3, max_slowdown=None),
        monitor=MonitorConfig(window=6, min_episodes=3, margin=0.1),
        cem=CemSettings(population=2, iterations=1, episodes_per_candidate=1),
        learner_preset="tiny",
    )
    return base.replace(**changes) if changes else base


def make_agent(report_dir: Path) -> PersistentAgent:
    identity = IdentityMemory.default()
    policy = DecompositionPolicy(identity=identity)
    return PersistentAgent(policy, identity, EpisodicMemory(report_dir / "agent" / "episodic.jsonl"))


def manifest_for(agent: PersistentAgent, config: EvolveConfig, root: Path) -> RunManifest:
    return RunManifest(
        task=TASK,
        modality="code",
        seed=0,
        perturbations=True,
        config=config,
        identity_hash=agent.identity_hash,
        mode="embedded",
        registry=str(root),
        learner="local",
        created_at=time.time(),
    )


def make_loop(
    tmp: Path,
    *,
    registry: Any,
    evaluator: Any,
    updater: Any,
    config: EvolveConfig | None = None,
    agent: PersistentAgent | None = None,
    progress: ProgressSink | None = None,
) -> EvolutionLoop:
    """A loop over the fakes, reporting into ``tmp/report`` (no Markdown report: fast)."""
    cfg = config or fake_config()
    report = tmp / "report"
    report.mkdir(parents=True, exist_ok=True)
    agent = agent or make_agent(report)
    return EvolutionLoop(
        task=TASK,
        config=cfg,
        registry=registry,
        evaluator=evaluator,
        updater=updater,
        agent=agent,
        report_dir=report,
        manifest=manifest_for(agent, cfg, tmp / "registry"),
        plan=PLAN,
        modality="code",
        progress=progress or RecordingProgress(),
        write_report=False,
    )


def seeded_registry(tmp: Path) -> LocalRegistry:
    registry = LocalRegistry(tmp / "registry", actor="tester")
    ensure_v0(registry, TASK, modality="code")
    return registry


# --- processes -------------------------------------------------------------------------------


def evolve_command(*args: str) -> list[str]:
    """``python -m capevo evolve ...`` when the lead has registered it, else the module itself."""
    from capevo.cli import main

    registered = "evolve" in getattr(main, "commands", {}) or "evolve" in getattr(main, "lazy_subcommands", {})
    head = [sys.executable, "-m", "capevo", "evolve"] if registered else [sys.executable, "-m", "capevo.cli.evolve"]
    return [*head, *args]


def child_env() -> dict[str, str]:
    """The environment for child processes: ours without CAPEVO_* settings that would redirect them."""
    return {k: v for k, v in os.environ.items() if not k.startswith("CAPEVO_")}


def run_cli(args: list[str], *, cwd: Path, timeout: float = 600.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=child_env())


class Child:
    """A child process whose stdout and stderr go to files ``<dir>/<name>.out`` and ``.err``."""

    def __init__(self, cmd: list[str], directory: Path, name: str, *, cwd: Path | None = None) -> None:
        self.name = name
        self.out_path = directory / f"{name}.out"
        self.err_path = directory / f"{name}.err"
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=child_env(), cwd=cwd or directory)

    def lines(self) -> list[dict[str, Any]]:
        """stdout's JSON objects (``READY {...}`` counts as ``{"event": "ready", ...}``)."""
        import json

        out = []
        for text in self.out_path.read_text(errors="replace").splitlines():
            text = text.strip()
            if text.startswith("READY "):
                text = text[len("READY ") :]
                with contextlib.suppress(ValueError):
                    out.append({"event": "ready", **json.loads(text)})
                continue
            try:
                value = json.loads(text)
            except ValueError:
                continue
            if isinstance(value, dict):
                out.append(value)
        return out

    def wait_event(self, event: str, timeout: float) -> dict[str, Any]:
        found: list[dict[str, Any]] = []

        def seen() -> bool:
            found[:] = [e for e in self.lines() if e.get("event") == event]
            return bool(found)

        if not wait_for(seen, timeout=timeout, proc=self.proc):
            raise AssertionError(f"{self.name}: no {event!r} within {timeout}s (exit {self.proc.poll()})\n{self.log()}")
        return found[0]

    def log(self) -> str:
        tail = self.err_path.read_text(errors="replace")[-4000:]
        return (
            f"--- {self.name} stdout ---\n{self.out_path.read_text(errors='replace')[-3000:]}\n--- stderr ---\n{tail}"
        )

    def stop(self, timeout: float = 60.0) -> int | None:
        """SIGTERM, then SIGKILL if it does not exit in time; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def wait_for(predicate: Callable[[], bool], *, timeout: float, proc: subprocess.Popen[Any] | None = None) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        if proc is not None and proc.poll() is not None:
            return predicate()
        time.sleep(0.05)
    return False


def kill(proc: subprocess.Popen[Any]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def registry_server(tmp_path: Path, endpoint: str) -> Child:
    """A registry server process on ``endpoint`` with its root under ``tmp_path``, ready."""
    registry = Child(
        [sys.executable, "-m", "capevo.registry.service", "--root", str(tmp_path / "registry"), "--listen", endpoint],
        tmp_path,
        "registry",
    )
    try:
        registry.wait_event("ready", timeout=60)
    except BaseException:
        registry.stop()
        raise
    return registry
