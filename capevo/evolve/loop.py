"""The closed loop: execute -> collect experience -> learn a new version -> gate -> promote or roll back.

One :class:`EvolutionLoop` evolves the ECMs of one task for a number of iterations while the
persistent agent A = (π_A, M_id, M_ep) stays fixed. Iteration i:

0. ``agent.begin_iteration(i)``: the identity hash is recomputed and compared with start-up
   (a change raises :class:`IdentityViolation` and stops the run); Δπ is recorded and must be
   exactly 0.
1. **Execute**: ``live_episodes`` episodes on fresh live seeds (:meth:`SeedPlan.live`) with the
   capability set active when the iteration started, every action through governance, each
   call's episodes written to one MCAP trace. Each episode is appended to M_ep, and the
   :class:`~capevo.runtime.monitor.DegradationMonitor` sees it (it rolls back a promoted
   version whose live success falls below its gate evidence).
2. **Collect**: the traces of those episodes are the experience.
3. **Update**: :func:`~capevo.learner.experience.pick_ecm_to_update` names the ECM where
   failed episodes most often ended; the updater of the modality learns a candidate on
   training seeds only; it is published (origin, parent and provenance from the learner).
   **Chains** (``updates_per_iteration`` ≠ 1, code modalities): a task fails until *every*
   step works, so one iteration may learn several ECMs in sequence. After each candidate, the
   ECM its own training episodes still blame most is learned next, with the chain's earlier
   candidates in place (companions); an ECM that still hands over in fewer than half of its
   episodes sends the chain to its predecessor (the fault may be in the state it is handed).
   The chain stops when the last candidate's episodes all succeed, at the limit, or when a
   learner finds nothing better. Its candidates are published, then gated as one change: the
   current set against the set with every member, one decision for all (the members were
   learned behind each other; judged one at a time, those that only work together were taken
   apart, see :mod:`capevo.runtime.gate`, "Chains").
   With ``--tie-siblings`` (``CemSettings.tie_siblings``), a search's candidate brings its
   siblings' (the same skill for T5's other objects, the same θ) into the chain with it.
   A candidate already waiting in the registry (published by a learner worker, or left by an
   interrupted run) is gated instead of learning another.
4. **Gate**: :class:`~capevo.runtime.gate.Gate` runs the active and the candidate version on
   the same fresh held-out gate seeds (:meth:`SeedPlan.gate`, round i), records the evidence
   in the registry and promotes (guarded by ``expected_active``) or rejects.
5. **Record**: one :class:`~capevo.evolve.metrics.IterationMetrics` row is appended durably.

After the last iteration the final capability set runs once more on iteration 0's live seeds
(the start-vs-final comparison of the report), and the report directory is written.

Resuming: finished iterations are the rows of ``metrics.jsonl``; the next run with the same
report directory and registry skips them and redoes the first unfinished one. The journal
(:mod:`capevo.evolve.state`) keeps a redone iteration exact: its live episodes run the
capability set the first attempt started with (same seeds, so the same outcomes), episodes
already in M_ep are not appended twice, a candidate the first attempt published is gated
rather than learned again, and a decision already taken is read back from the registry.

Invariants:
1. The identity hash is checked at the start of every iteration and of every resumed run; Δπ
   of every recorded iteration is exactly 0.0.
2. Every candidate the loop publishes is gated within the same iteration (unless the run is
   interrupted); every gate decision is preceded by a ``gate`` audit event with its evidence.
3. Learners see training seeds only; gate seeds are held out (the gate refuses others); live
   seeds of different iterations are disjoint.
4. ``metrics.jsonl`` has one row per finished iteration, 0..k-1, never a row for an
   unfinished one; an iteration's row is written after its gate decision is in the registry.
5. Redoing an interrupted iteration appends no episode to M_ep twice.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capevo.agent import EpisodeRecord, PersistentAgent
from capevo.errors import CapevoError, Conflict, IdentityViolation, NotFound, Unavailable
from capevo.evolve.config import NEURAL_MODALITIES, EvolveConfig
from capevo.evolve.learners import Proposal, Updater, UpdateRequest, waiting_candidates
from capevo.evolve.metrics import (
    ChainUpdate,
    GateSummary,
    IterationMetrics,
    MetricsLog,
    outcome_stats,
    split_monitor_actions,
)
from capevo.evolve.progress import ProgressSink, RecordingProgress
from capevo.evolve.state import Journal, RunManifest, load_manifest, save_manifest
from capevo.records import EcmVersion, State
from capevo.registry.api import Registry
from capevo.runtime.evaluation import EpisodeOutcome, Evaluator
from capevo.runtime.gate import Gate, SeedPlan
from capevo.runtime.monitor import DegradationMonitor
from capevo.runtime.tasks import task_spec

log = logging.getLogger(__name__)

ACTOR = "evolve"
"""Audit actor of the loop's own registry mutations (v0 creation, publishing candidates)."""
GATE_ACTOR = "evolve-gate"
MONITOR_ACTOR = "evolve-monitor"
TRACE_PHASES = ("live", "gate", "final")
UPSTREAM_BELOW = 0.5
"""A chain learns the predecessor of an ECM whose new version still hands over in fewer than
this fraction of its own training episodes."""


# --- version 0 ----------------------------------------------------------------------------


def ensure_v0(
    registry: Registry, task: str, *, modality: str, net_arch: Sequence[int] = (256, 256), seed: int = 0
) -> list[EcmVersion]:
    """Create version 0 of every ECM of ``task`` the registry lacks, and make it active.

    This is the paper's *manual creation*: code ECMs get the built-in parametric skills with
    their untuned parameters (:func:`capevo.learner.skills.seed_specs`), neural ECMs (``rl``,
    ``il``) randomly initialised SAC policies (:func:`capevo.learner.neural_seed.seed_policy`).
    Both are published with origin ``manual`` and promoted without a gate. An ECM that exists
    but has no active version (seeding interrupted between publish and promote) gets its
    latest manual candidate promoted.

    Returns:
        The versions created or promoted now (empty when every ECM already had an active one).
    """
    spec = task_spec(task)
    existing = {s.name: s for s in registry.list_ecms()}
    missing = [n for n in spec.ecm_names if n not in existing]
    out: list[EcmVersion] = []
    if missing:
        if modality in NEURAL_MODALITIES:
            from capevo.learner.neural_seed import seed_neural_registry

            out.extend(
                seed_neural_registry(
                    registry,
                    spec.name,
                    ecms=missing,
                    net_arch=net_arch,
                    seed=seed,
                    reason="v0: manual creation (randomly initialised neural policy)",
                )
            )
        else:
            from capevo.learner.skills import seed_registry

            out.extend(seed_registry(registry, spec.name, reason="v0: manual creation (built-in untuned skill)"))
    for name in spec.ecm_names:
        if name in missing:
            continue
        if existing[name].active_version is None:
            manual = [
                v for v in registry.get_ecm(name).versions if v.state is State.CANDIDATE and v.origin.value == "manual"
            ]
            if manual:
                out.append(
                    registry.promote(name, manual[-1].version, reason="v0: manual creation (completing a seeding)")
                )
    return out


def task_capability_set(registry: Registry, task: str) -> dict[str, int]:
    """The active version of each ECM of ``task``.

    Raises:
        NotFound: an ECM of the task has no active version.
    """
    active = registry.capability_set().active
    names = task_spec(task).ecm_names
    missing = [n for n in names if n not in active]
    if missing:
        raise NotFound(f"no active version of {', '.join(missing)}", details={"missing": missing})
    return {n: int(active[n]) for n in names}


# --- evaluation with progress -------------------------------------------------------------


class PhaseEvaluator:
    """The loop's evaluator: routes each phase's traces to its own directory, counts episodes,
    and (for remote workers) waits for a worker to appear.

    Args:
        inner: A :class:`~capevo.runtime.evaluator.LocalEvaluator` or a remote one.
        trace_root: ``<trace_root>/<phase>/`` receives a local evaluator's traces.
        progress: Told about every finished episode.
        wait_for_worker_s: How long an ``Unavailable`` (no runtime worker yet) is retried.
    """

    def __init__(
        self,
        inner: Evaluator,
        *,
        trace_root: Path | None,
        progress: ProgressSink,
        wait_for_worker_s: float = 0.0,
    ) -> None:
        self.inner = inner
        self.trace_root = trace_root
        self.progress = progress
        self.wait_for_worker_s = wait_for_worker_s
        self.phase = "live"
        self._local = hasattr(inner, "trace_dir") and hasattr(inner, "progress")
        self.env_steps: dict[str, int] = {}
        """Env steps of the episodes run, by phase (the loop resets it every iteration)."""

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        # a remote evaluator given a trace_dir copies the workers' traces there: route them too
        if self.trace_root is not None and (self._local or getattr(self.inner, "trace_dir", None) is not None):
            directory = self.trace_root / self.phase
            directory.mkdir(parents=True, exist_ok=True)
            self.inner.trace_dir = directory  # type: ignore[attr-defined]
        if self._local:
            self.inner.progress = lambda done, total, outcome: self.progress.episodes_done(1)  # type: ignore[attr-defined]
        deadline = time.monotonic() + self.wait_for_worker_s
        while True:
            try:
                out = list(self.inner.evaluate(task, versions, seeds))
                break
            except Unavailable as exc:
                if time.monotonic() >= deadline:
                    raise
                log.info("no runtime worker yet (%s); retrying", exc)
                time.sleep(1.0)
        if not self._local:
            self.progress.episodes_done(len(out))
        self.env_steps[self.phase] = self.env_steps.get(self.phase, 0) + sum(int(o.steps) for o in out)
        return out


# --- the loop -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class FinalEvaluation:
    """The final capability set on iteration 0's live seeds, next to iteration 0 itself."""

    seeds: tuple[int, ...]
    start_versions: Mapping[str, int]
    final_versions: Mapping[str, int]
    start: tuple[EpisodeOutcome, ...]
    final: tuple[EpisodeOutcome, ...]
    comparison: Mapping[str, Any] | None
    """Paired statistics (McNemar, Tango, Wilcoxon) final vs start; None when identical sets."""


@dataclass(frozen=True, slots=True, kw_only=True)
class EvolveResult:
    """What :meth:`EvolutionLoop.run` did."""

    task: str
    report_dir: Path
    rows: tuple[IterationMetrics, ...]
    final: FinalEvaluation | None
    identity_hash: str
    delta_pi: float
    created: tuple[EcmVersion, ...]
    """Versions 0 created by this run (empty on a resumed or pre-seeded registry)."""
    resumed_from: int
    """Iterations already finished when this run started."""
    wall_s: float
    report_files: tuple[Path, ...] = field(default_factory=tuple)


class EvolutionLoop:
    """The closed loop of one task (see the module docstring).

    Args:
        task: Task id or name.
        config: Budgets.
        registry: Where versions live (local or remote); not closed here.
        evaluator: Runs episodes (live, gate, final): a LocalEvaluator or a RemoteEvaluator.
        updater: Produces candidates (in-process learner or remote learners).
        agent: The persistent agent; its episodic memory receives the live episodes.
        report_dir: Metrics, journal, traces, report.
        manifest: The run's fixed facts (checked against the one on disk when resuming).
        plan: Disjoint train/gate/live seeds.
        modality: Recorded in the report.
        progress: Display sink.
        trace_root: Where a local evaluator writes traces (per phase); default ``report_dir/traces``.
        wait_for_worker_s: With remote workers, how long to wait for one to appear.
        write_report: Write the Markdown report and plots at the end.

    Raises:
        IdentityViolation, Invalid: the report directory holds a run that cannot be continued.
    """

    def __init__(
        self,
        *,
        task: str,
        config: EvolveConfig,
        registry: Registry,
        evaluator: Evaluator,
        updater: Updater,
        agent: PersistentAgent,
        report_dir: Path,
        manifest: RunManifest,
        plan: SeedPlan,
        modality: str,
        progress: ProgressSink | None = None,
        trace_root: Path | None = None,
        wait_for_worker_s: float = 0.0,
        write_report: bool = True,
        created: Sequence[EcmVersion] = (),
    ) -> None:
        self.spec = task_spec(task)
        self.task = self.spec.name
        self.config = config
        self.registry = registry
        self.updater = updater
        self.agent = agent
        self.report_dir = Path(report_dir)
        self.report_dir.mkdir(parents=True, exist_ok=True)
        self.plan = plan
        self.modality = modality
        self.progress: ProgressSink = progress if progress is not None else RecordingProgress()
        self.write_report = write_report
        self.created = tuple(created)
        config.check_budget(self.task, modality=modality)
        on_disk = load_manifest(self.report_dir)
        if on_disk is not None:
            on_disk.check_resume(manifest)
            if on_disk.config.iterations != manifest.config.iterations:
                # a resumed run may be given more (or fewer) iterations: the manifest keeps the
                # current target, so the report never reads "6 of 3 iterations finished"
                on_disk = dataclasses.replace(
                    on_disk, config=dataclasses.replace(on_disk.config, iterations=manifest.config.iterations)
                )
                save_manifest(self.report_dir, on_disk)
            self.manifest = on_disk
        else:
            save_manifest(self.report_dir, manifest)
            self.manifest = manifest
        self.metrics = MetricsLog(self.report_dir)
        self.journal = Journal(self.report_dir)
        self.evaluator = PhaseEvaluator(
            evaluator,
            trace_root=trace_root if trace_root is not None else self.report_dir / "traces",
            progress=self.progress,
            wait_for_worker_s=wait_for_worker_s,
        )
        self.monitor_actions: list[dict[str, Any]] = []
        self.monitor = DegradationMonitor(
            registry,  # type: ignore[arg-type]
            config=config.monitor,
            actor=MONITOR_ACTOR,
            on_action=lambda a: self.monitor_actions.append(a.to_dict()),
            replay=self._monitor_replay,
        )
        self.gate = Gate(
            registry,  # type: ignore[arg-type]
            self.evaluator,
            config.gate,
            actor=GATE_ACTOR,
            seed_plan=plan,
            progress=self._gate_progress,
        )
        self._remembered = self._episodes_in_memory()
        self._learned = (0, 0)
        """(episodes, env steps) of every proposal the current update attempt made, kept or not."""

    # --- helpers ---------------------------------------------------------------------------

    def _episodes_in_memory(self) -> set[tuple[int, int]]:
        try:
            log_ = self.agent.episodic_memory.read()
        except NotFound:
            return set()
        return {(r.iteration, r.seed) for r in log_.records if r.task == self.task}

    def _monitor_replay(self, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        """The degradation monitor's confirmation episodes: their own phase, traces and env steps."""
        before = self.evaluator.phase
        self.evaluator.phase = "monitor"
        self.progress.phase("monitor", episodes=len(seeds))
        try:
            return self.evaluator.evaluate(self.task, versions, seeds)
        finally:
            self.evaluator.phase = before

    def _gate_progress(self, stage: str, message: str) -> None:
        if stage in ("extend", "decided", "promoted", "rejected"):
            self.progress.message(f"  {message}")
        if stage == "extend":
            self.progress.phase("gate", episodes=2 * self.config.gate.extend_n)

    # --- run -----------------------------------------------------------------------------

    def run(self, *, should_stop: Callable[[], bool] | None = None) -> EvolveResult:
        """Run (or continue) the loop to ``config.iterations`` and write the report.

        Raises:
            IdentityViolation: the agent changed (stops the run at once).
            CapevoError: the registry or the runtime failed in a way the loop cannot absorb.
        """
        started = time.perf_counter()
        resumed_from = self.metrics.completed
        total = self.config.iterations
        self.progress.run_started(task=self.task, total=total, completed=min(resumed_from, total))
        if resumed_from:
            self.progress.message(
                f"resuming {self.task}: {resumed_from} iteration(s) already done in {self.report_dir}"
            )
        for i in range(resumed_from, total):
            if should_stop is not None and should_stop():
                break
            self.iteration(i)
        final = None
        if self.config.final_evaluation and self.metrics.completed >= total and self.metrics.completed > 0:
            final = self.final_evaluation()
        rows = self.metrics.rows
        result = EvolveResult(
            task=self.task,
            report_dir=self.report_dir,
            rows=rows,
            final=final,
            identity_hash=self.agent.identity_hash,
            delta_pi=self.agent.policy_drift(),
            created=self.created,
            resumed_from=resumed_from,
            wall_s=time.perf_counter() - started,
        )
        if self.write_report:
            from capevo.evolve.report import write_report

            files = write_report(self.report_dir, registry=self.registry, manifest=self.manifest, final=final)
            result = EvolveResult(**{**_fields(result), "report_files": tuple(files)})
        return result

    # --- one iteration ----------------------------------------------------------------------

    def iteration(self, i: int) -> IterationMetrics:
        """Run iteration ``i`` (or redo it after an interruption) and append its metrics row.

        Raises:
            IdentityViolation: the agent's identity changed, or Δπ is not 0.
        """
        t0 = time.perf_counter()
        started_at = time.time()
        self.progress.iteration_started(i)
        delta_pi = self.agent.begin_iteration(i)
        identity = self.agent.check_identity()
        if delta_pi != 0.0:
            raise IdentityViolation(
                f"policy drift Δπ = {delta_pi!r} at iteration {i}: the agent's policy parameters changed",
                details={"iteration": i, "delta_pi": delta_pi},
            )
        start = self.journal.last(i, "start")
        if start is None:
            caps = task_capability_set(self.registry, self.task)
            start = self.journal.write(
                "start", i, capability_set=caps, revision=self.registry.capability_set().revision
            )
        caps = {str(k): int(v) for k, v in start["capability_set"].items()}
        self.evaluator.env_steps = {}

        # 1-2. execute and collect
        seeds = self.plan.live(self.config.live_episodes, offset=i * self.config.live_episodes)
        self.progress.phase("live", episodes=len(seeds))
        self.evaluator.phase = "live"
        t_live = time.perf_counter()
        outcomes = self.evaluator.evaluate(self.task, caps, seeds)
        wall_live = time.perf_counter() - t_live
        for o in outcomes:
            if (i, o.seed) not in self._remembered:
                self.agent.remember(EpisodeRecord.from_outcome(iteration=i, task=self.task, outcome=o))
                self._remembered.add((i, o.seed))
        self.monitor_actions.clear()
        self.monitor.observe_many(outcomes)
        rollbacks = tuple(self.monitor_actions)
        for r in rollbacks:
            self.progress.message(f"  {r['reason']}")

        # 3-4. update and gate
        t_learn = time.perf_counter()
        update = self._update(i, outcomes)
        wall_learn = time.perf_counter() - t_learn - update.gate_s

        row = IterationMetrics(
            iteration=i,
            started_at=started_at,
            live=outcome_stats(outcomes),
            live_seeds=tuple(seeds),
            episodes=tuple(o.to_dict() for o in outcomes),
            delta_pi=delta_pi,
            identity_hash=identity,
            active_versions=caps,
            active_after=task_capability_set(self.registry, self.task),
            ecm_updated=update.ecm,
            candidate_version=update.version,
            learner=update.learner,
            learner_episodes=update.episodes,
            learner_steps=update.steps,
            env_steps_live=self.evaluator.env_steps.get("live", 0),
            env_steps_gate=self.evaluator.env_steps.get("gate", 0),
            env_steps_monitor=self.evaluator.env_steps.get("monitor", 0),
            gate=update.gate,
            further=tuple(u.summary() for u in update.further),
            update_note=update.note,
            rollbacks=rollbacks,
            wall_live_s=wall_live,
            wall_learn_s=max(wall_learn, 0.0),
            wall_gate_s=update.gate_s,
            wall_s=time.perf_counter() - t0,
            traces=tuple(dict.fromkeys(o.trace_path for o in outcomes if o.trace_path)),
        )
        self.metrics.append(row)
        self.progress.iteration_finished(i, _summary_line(row))
        return row

    def _update(self, i: int, outcomes: Sequence[EpisodeOutcome]) -> _Update:
        decided = self.journal.last(i, "decided")
        if decided is not None:
            # The interrupted attempt got as far as the decision: read it back, do not redo it.
            update = _Update.from_journal(decided)
            update.further = [_Update.from_journal(d) for d in decided.get("further") or []]
            return update
        chain = self.journal.last(i, "chain")
        if chain is not None:
            members = list(chain["members"])
            records = [self.registry.get_version(m["ecm"], int(m["version"])) for m in members]
            note = "resumed: gating the chain the interrupted attempt published"
            return self._finish(i, self._decide_chain(i, records, members, note=note))
        cand = self.journal.last(i, "candidate")
        if cand is not None:
            record = self.registry.get_version(cand["ecm"], int(cand["version"]))
            note = (
                "resumed: gating the candidate the interrupted attempt published"
                if record.state is State.CANDIDATE
                else "resumed"
            )
            update = self._gate_one(
                i,
                record,
                learner=cand.get("learner"),
                episodes=cand.get("episodes", 0),
                steps=cand.get("steps", 0),
                note=note,
            )
            return self._finish(i, update)
        waiting = waiting_candidates(self.registry, self.spec.ecm_names)
        if waiting:
            record = waiting[0]
            learner = record.provenance.learner_id or f"published by {record.created_by}"
            self.journal.write("candidate", i, ecm=record.name, version=record.version, learner=learner, adopted=True)
            note = f"gated a waiting candidate published by {record.created_by}"
            return self._finish(i, self._gate_one(i, record, learner=learner, note=note))
        from capevo.learner.experience import pick_ecm_to_update

        ecm = pick_ecm_to_update(list(outcomes), self.spec.ecm_names)
        pick_note = ""
        if ecm is None:
            if all(o.success for o in outcomes):
                return self._finish(i, _Update(note="no live episode failed: nothing to improve"))
            # Failures but no readable trace (e.g. a remote worker's files are on another host):
            # fix upstream first.
            ecm = self.spec.ecm_names[0]
            pick_note = f"no readable traces of the failed episodes; updating the first step {ecm}"
        self.progress.message(f"  learn: {ecm} with {self.updater.name}")
        request = self._update_request(i, ecm, outcomes, slot=i * self._chain_limit())
        self._learned = (0, 0)
        try:
            proposal = self._propose(request)
        except (IdentityViolation, KeyboardInterrupt):
            raise
        except CapevoError as exc:
            log.warning("learner for %s failed: %s", ecm, exc)
            return self._finish(i, _Update(ecm=ecm, learner=self.updater.name, note=f"learner failed: {exc}"))
        if proposal is None:
            return self._finish(
                i, _Update(ecm=ecm, learner=self.updater.name, note=f"no candidate from {self.updater.name}")
            )
        if proposal.candidate is not None and self._same_as_parent(proposal):
            return self._finish(
                i,
                _Update(
                    ecm=ecm,
                    learner=proposal.learner,
                    episodes=proposal.episodes,
                    steps=proposal.steps,
                    note=f"{proposal.learner} found nothing better than the parent on its training seeds: "
                    "no candidate published",
                ),
            )
        note = pick_note
        if proposal.notes.get("fallback"):
            note = (note + "; " if note else "") + f"fallback: {proposal.notes['fallback']}"
        if proposal.notes.get("check"):
            from capevo.learner.rl import check_note

            note = (note + "; " if note else "") + check_note(proposal.notes["check"])
        chain, chain_note, spent = self._extend_chain(i, ecm, proposal, outcomes)
        if len(chain) > 1:
            return self._publish_chain(i, chain, note="; ".join(n for n in (note, chain_note) if n), spent=spent)
        # the chain may have learned the first ECM again: its latest candidate is the one to gate
        proposal = chain[0][1]
        record = self._publish(proposal)
        self.journal.write(
            "candidate",
            i,
            ecm=record.name,
            version=record.version,
            learner=proposal.learner,
            episodes=proposal.episodes + spent[0],
            steps=proposal.steps + spent[1],
        )
        note = "; ".join(n for n in (note, chain_note) if n)
        update = self._gate_one(
            i,
            record,
            learner=proposal.learner,
            episodes=proposal.episodes + spent[0],
            steps=proposal.steps + spent[1],
            note=note,
        )
        return self._finish(i, update)

    # --- chains: several ECMs learned in one iteration ---------------------------------------

    def _chain_limit(self) -> int:
        """Most updates one iteration may learn (1 unless the updater can chain)."""
        if not getattr(self.updater, "supports_companions", False):
            return 1
        return self.config.updates_per_iteration or len(self.spec.ecm_names)

    def _extend_chain(
        self, i: int, ecm: str, first: Proposal, outcomes: Sequence[EpisodeOutcome]
    ) -> tuple[list[tuple[str, Proposal]], str, tuple[int, int]]:
        """Learn the ECMs the latest candidate's own training episodes still fail on.

        Each next ECM is :func:`~capevo.learner.experience.pick_ecm_to_update` over the previous
        candidate's training episodes, learned behind every candidate of the chain so far
        (companions); an ECM already in the chain is learned again from its chain candidate.
        Exceptions: an ECM with steps the safety monitor graded unsafe in those episodes is learned
        next, once per chain, even if they succeeded (safety ranks first in the search); when the
        ECM just learned still hands over in fewer than
        :data:`UPSTREAM_BELOW` of its own episodes, the fault may lie in the state it is handed
        (a lift that drops an object the grasp barely holds), so its predecessor in the
        decomposition is learned next (once per ECM and chain); so is the predecessor of an ECM
        for which the learner found nothing better (once). The chain stops when those episodes
        all succeeded, the limit is reached, or a learner brings nothing better twice. A
        candidate's tied candidates (``--tie-siblings``) join the chain with it, replacing any
        earlier member of theirs.

        Returns:
            ``(ecm, proposal)`` per ECM in decomposition order (one per ECM, its latest
            candidate), a note on why the chain stopped, and the (episodes, steps) the learner
            spent on candidates the chain dropped or replaced by a later one of the same ECM (the
            budget counts every update learned, not only those gated).
        """
        from capevo.learner.experience import handover_rate, pick_ecm_to_update, unsafe_ecm

        names = list(self.spec.ecm_names)
        limit = self._chain_limit()
        members: dict[str, Proposal] = {ecm: first, **_tied_proposals(first)}
        latest, latest_ecm = first, ecm
        went_upstream: set[str] = set()
        made_safe: set[str] = set()
        forced: str | None = None
        why = ""
        for k in range(1, limit):
            experience = list(latest.experience)
            if not experience:
                break
            index = names.index(latest_ecm)
            unsafe = unsafe_ecm(experience, names)
            nxt: str | None
            if forced is not None:
                nxt, forced = forced, None
            elif unsafe is not None and unsafe not in made_safe:
                # the gate rejects a version that is unsafe more often: make that step safe first
                made_safe.add(unsafe)
                nxt = unsafe
            elif all(o.success for o in experience):
                why = "chain: the last candidate succeeded on all its training episodes"
                break
            elif (
                index > 0
                and latest_ecm not in went_upstream
                and handover_rate(experience, names, latest_ecm) < UPSTREAM_BELOW
            ):
                went_upstream.add(latest_ecm)
                nxt = names[index - 1]
            else:
                nxt = pick_ecm_to_update(experience, names)
            if nxt is None:
                break
            companions = {e: p.candidate.artifact for e, p in members.items() if e != nxt and p.candidate is not None}
            start = members.get(nxt)
            source = start.candidate.source if start is not None and start.candidate is not None else None
            spent = self._learned[1]
            cap = self._learner_cap(learner_spent=spent)
            if cap is not None and cap < self._smallest_update():
                why = "chain stopped: the iteration's env-step budget is spent"
                break
            self.progress.message(f"  learn: {nxt} with {self.updater.name} (chain step {k + 1})")
            request = self._update_request(
                i,
                nxt,
                outcomes,
                slot=i * limit + k,
                companions=companions,
                source=source,
                learner_spent=spent,
            )
            try:
                proposal = self._propose(request)
            except (IdentityViolation, KeyboardInterrupt):
                raise
            except CapevoError as exc:
                log.warning("chain learner for %s failed: %s", nxt, exc)
                why = f"chain stopped: learner for {nxt} failed: {exc}"
                break
            cand = proposal.candidate if proposal is not None else None
            if proposal is None or cand is None:
                why = f"chain stopped: no candidate for {nxt}"
                break
            unchanged = source.encode() == cand.artifact if source is not None else self._same_as_parent(proposal)
            if unchanged or not cand.improved:
                where = names.index(nxt)
                if where > 0 and nxt not in went_upstream:
                    # nothing better for this step: the fault may be in what it is handed
                    went_upstream.add(nxt)
                    forced = names[where - 1]
                    why = f"chain: {proposal.learner} found nothing better for {nxt}; tried {forced}"
                    continue
                why = f"chain stopped: {proposal.learner} found nothing better for {nxt}"
                break
            members[nxt] = proposal
            members.update(_tied_proposals(proposal))
            latest, latest_ecm = proposal, nxt
        chain = sorted(members.items(), key=lambda kv: names.index(kv[0]))
        # every update learned counts, also those dropped or replaced by a later one of the same ECM
        dropped = (
            self._learned[0] - sum(p.episodes for p in members.values()),
            self._learned[1] - sum(p.steps for p in members.values()),
        )
        return chain, why, dropped

    def _propose(self, request: UpdateRequest) -> Proposal | None:
        """The updater's proposal for ``request``, its episodes and steps added to :attr:`_learned`."""
        proposal = self.updater.propose(request, self.progress)
        if proposal is not None:
            self._learned = (self._learned[0] + proposal.episodes, self._learned[1] + proposal.steps)
        return proposal

    def _update_request(
        self,
        i: int,
        ecm: str,
        outcomes: Sequence[EpisodeOutcome],
        *,
        slot: int,
        companions: Mapping[str, bytes] | None = None,
        source: str | None = None,
        learner_spent: int = 0,
    ) -> UpdateRequest:
        return UpdateRequest(
            max_env_steps=self._learner_cap(learner_spent=learner_spent),
            task=self.task,
            ecm=ecm,
            iteration=i,
            outcomes=tuple(outcomes),
            plan=self.plan,
            seed=self.manifest.seed,
            companions=dict(companions or {}),
            source=source,
            slot=slot,
        )

    def _smallest_update(self) -> int:
        return self.config.smallest_update(self.task, modality=self.modality)

    def _learner_cap(self, *, learner_spent: int) -> int | None:
        """Env steps the next learner may spend: the iteration's budget less the live steps
        taken (and the monitor's confirmation episodes, which come out of the learner's share),
        the learner steps the chain took already, and one gate at the horizon (a chain is gated
        as one change) (None: no budget)."""
        budget = self.config.env_steps_per_iteration
        if budget is None:
            return None
        h = self.config.episode_steps_max(self.task)
        taken = self.evaluator.env_steps.get("live", 0) + self.evaluator.env_steps.get("monitor", 0)
        return budget - taken - learner_spent - 2 * self.config.gate_seeds_max * h

    def _publish_chain(
        self, i: int, chain: Sequence[tuple[str, Proposal]], *, note: str, spent: tuple[int, int] = (0, 0)
    ) -> _Update:
        members = []
        records = []
        for _, proposal in chain:
            record = self._publish(proposal)
            records.append(record)
            members.append(
                {
                    "ecm": record.name,
                    "version": record.version,
                    "learner": proposal.learner,
                    "episodes": proposal.episodes + (spent[0] if not members else 0),
                    "steps": proposal.steps + (spent[1] if not members else 0),
                }
            )
        # one durable record of the whole chain: a redone iteration gates exactly these
        self.journal.write("chain", i, members=members)
        return self._finish(i, self._decide_chain(i, records, members, note=note))

    def _decide_chain(
        self, i: int, records: Sequence[EcmVersion], members: Sequence[Mapping[str, Any]], *, note: str
    ) -> _Update:
        """Gate a chain's candidates as one change: the current set against the set with every
        member, on the same held-out seeds, one decision for all (see :mod:`capevo.runtime.gate`,
        "Chains": the members were learned behind each other, and judged one at a time those
        that only work together were rejected). A decision an interrupted attempt recorded is
        finished from its evidence, not gated again.
        """
        first, rest = records[0], records[1:]
        chain = {r.name: r.version for r in records}
        recorded = self._recorded_chain_evidence(chain)
        if recorded is not None:
            self.gate.settle(recorded)
        update = self._gate_one(
            i,
            self.registry.get_version(first.name, first.version),
            learner=members[0].get("learner"),
            episodes=int(members[0].get("episodes") or 0),
            steps=int(members[0].get("steps") or 0),
            note=note,
            companions={r.name: r.version for r in rest},
        )
        for k, record in enumerate(rest, start=1):
            evidence = self.registry.get_version(record.name, record.version).gate_evidence
            update.further.append(
                _Update(
                    ecm=record.name,
                    version=record.version,
                    learner=members[k].get("learner"),
                    episodes=int(members[k].get("episodes") or 0),
                    steps=int(members[k].get("steps") or 0),
                    gate=GateSummary.from_evidence(evidence, reason="decided with the chain") if evidence else None,
                    note=f"decided with {first.name} v{first.version}",
                )
            )
        update.episodes += sum(u.episodes for u in update.further)
        update.steps += sum(u.steps for u in update.further)
        return update

    def _recorded_chain_evidence(self, chain: Mapping[str, int]) -> Mapping[str, Any] | None:
        """The gate evidence of exactly this chain that some member carries already, if any."""
        for name, version in chain.items():
            evidence = self.registry.get_version(name, version).gate_evidence
            if evidence and evidence.get("chain") == dict(chain):
                return evidence
        return None

    def _same_as_parent(self, proposal: Proposal) -> bool:
        cand = proposal.candidate
        if cand is None or cand.spec.parent is None:
            return False
        try:
            parent = self.registry.get_version(cand.ecm, cand.spec.parent)
        except NotFound:
            return False
        return parent.artifact.sha256 == hashlib.sha256(cand.artifact).hexdigest()

    def _publish(self, proposal: Proposal) -> EcmVersion:
        if proposal.record is not None:
            return proposal.record
        cand = proposal.candidate
        assert cand is not None  # Proposal invariant 2
        try:
            return self.registry.publish(cand.ecm, cand.artifact, cand.spec, actor=ACTOR)  # type: ignore[call-arg]
        except TypeError:
            return self.registry.publish(cand.ecm, cand.artifact, cand.spec)

    def _gate_one(
        self,
        i: int,
        record: EcmVersion,
        *,
        learner: str | None,
        episodes: int = 0,
        steps: int = 0,
        note: str = "",
        companions: Mapping[str, int] | None = None,
    ) -> _Update:
        """Gate ``record`` (with ``companions``, the rest of its chain, decided together), or read
        the decision back when it was made already."""
        update = _Update(
            ecm=record.name,
            version=record.version,
            learner=learner,
            episodes=int(episodes),
            steps=int(steps),
            note=note,
        )
        if record.state is not State.CANDIDATE:
            # Decided already (by the interrupted attempt, or by someone else): read the evidence.
            gate = None
            if record.gate_evidence:
                gate = GateSummary.from_evidence(record.gate_evidence, reason="read back from the registry")
            update.gate = gate
            if gate is None:
                update.note = (
                    update.note + "; " if update.note else ""
                ) + f"{record.state.value} without gate evidence"
            return update
        seeds = self.plan.gate(self.config.gate_episodes, round=i)
        extend_n = self.config.gate.extend_n
        extension = self.plan.gate_extension(extend_n, round=i) if extend_n else []
        try:
            self.registry.get_version(record.name)
            paired = True
        except NotFound:
            paired = False
        self.progress.phase("gate", episodes=len(seeds) * (2 if paired else 1))
        self.evaluator.phase = "gate"
        t = time.perf_counter()
        try:
            decision = self.gate.run(
                record.name,
                record.version,
                task=self.task,
                seeds=seeds,
                extension_seeds=extension,
                with_candidates=companions,
            )
        except Conflict as exc:
            update.gate_s = time.perf_counter() - t
            update.note = (update.note + "; " if update.note else "") + f"gate conflict: {exc.message}"
            return update
        update.gate_s = time.perf_counter() - t
        update.gate = GateSummary.from_evidence(decision.evidence, reason=decision.reason)
        return update

    def _finish(self, i: int, update: _Update) -> _Update:
        self.journal.write(
            "decided",
            i,
            ecm=update.ecm,
            version=update.version,
            learner=update.learner,
            learner_episodes=update.episodes,
            learner_steps=update.steps,
            gate=update.gate.to_dict() if update.gate is not None else None,
            note=update.note,
            further=[u.journal_fields() for u in update.further],
        )
        return update

    # --- final evaluation -------------------------------------------------------------------

    def final_evaluation(self) -> FinalEvaluation | None:
        """Run the final capability set on iteration 0's live seeds (reused if already run)."""
        rows = self.metrics.rows
        if not rows:
            return None
        first = rows[0]
        seeds = list(first.live_seeds)
        start = tuple(EpisodeOutcome.from_dict(e) for e in first.episodes)
        final_versions = task_capability_set(self.registry, self.task)
        done = self.journal.final()
        if done is not None and done.get("capability_set") == final_versions and list(done.get("seeds") or []) == seeds:
            final = tuple(EpisodeOutcome.from_dict(o) for o in done["outcomes"])
        elif final_versions == dict(first.active_versions):
            final = start
        else:
            self.progress.phase("final", episodes=len(seeds))
            self.evaluator.phase = "final"
            final = tuple(self.evaluator.evaluate(self.task, final_versions, seeds))
            self.journal.write(
                "final",
                len(rows),
                capability_set=final_versions,
                seeds=seeds,
                outcomes=[o.to_dict() for o in final],
            )
        comparison = None
        if final is not start:
            from capevo.runtime.gate_stats import paired_stats

            comparison = paired_stats(
                list(start), list(final), alpha=self.config.gate.alpha, margin=self.config.gate.delta
            ).to_dict()
        return FinalEvaluation(
            seeds=tuple(seeds),
            start_versions=dict(first.active_versions),
            final_versions=final_versions,
            start=start,
            final=final,
            comparison=comparison,
        )


@dataclass(slots=True, kw_only=True)
class _Update:
    ecm: str | None = None
    version: int | None = None
    learner: str | None = None
    episodes: int = 0
    steps: int = 0
    gate: GateSummary | None = None
    note: str = ""
    gate_s: float = 0.0
    further: list[_Update] = field(default_factory=list)
    """The later updates of a chain (the first one is this)."""

    def journal_fields(self) -> dict[str, Any]:
        return {
            "ecm": self.ecm,
            "version": self.version,
            "learner": self.learner,
            "learner_episodes": self.episodes,
            "learner_steps": self.steps,
            "gate": self.gate.to_dict() if self.gate is not None else None,
            "note": self.note,
        }

    @classmethod
    def from_journal(cls, d: Mapping[str, Any]) -> _Update:
        return cls(
            ecm=d.get("ecm"),
            version=d.get("version"),
            learner=d.get("learner"),
            episodes=int(d.get("learner_episodes") or 0),
            steps=int(d.get("learner_steps") or 0),
            gate=GateSummary.from_dict(d["gate"]) if d.get("gate") else None,
            note=str(d.get("note") or ""),
        )

    def summary(self) -> ChainUpdate:
        return ChainUpdate(ecm=self.ecm, version=self.version, learner=self.learner, gate=self.gate, note=self.note)


def _fields(result: EvolveResult) -> dict[str, Any]:
    return {name: getattr(result, name) for name in EvolveResult.__dataclass_fields__}


def _tied_proposals(proposal: Proposal) -> dict[str, Proposal]:
    """Chain members for the candidates tied to ``proposal``'s: the same θ from the same search,
    so they carry no episodes or steps of their own (the search's are counted once, on it)."""
    cand = proposal.candidate
    if cand is None:
        return {}
    return {t.ecm: Proposal(learner=f"{proposal.learner} (tied to {cand.ecm})", candidate=t) for t in cand.tied}


def _summary_line(row: IterationMetrics) -> str:
    s = row.live
    parts = [
        f"success {s.successes}/{s.episodes}",
        f"reward {s.reward_mean:.2f} (σ² {s.reward_var:.2f})",
        f"interventions {s.interventions}",
        f"unsafe {s.unsafe_steps}",
        f"Δπ {row.delta_pi:g}",
    ]
    if row.gate is not None:
        g = row.gate
        gate = f"{g.decision} {g.ecm} v{g.candidate_version} ({g.candidate_successes}/{g.n}"
        if g.active_successes is not None:
            gate += f" vs {g.active_successes}/{g.n}"
        parts.append(gate + ")")
    elif row.update_note:
        parts.append(row.update_note)
    rolled, kept = split_monitor_actions(row.rollbacks)
    if rolled:
        parts.append("rolled back " + ", ".join(f"{r['name']} v{r['version']}" for r in rolled))
    if kept:
        kept_names = ", ".join(f"{r['name']} v{r['version']}" for r in kept)
        parts.append(f"kept {kept_names} (drop not confirmed on the same seeds)")
    parts.append(f"{row.wall_s:.0f}s")
    return "; ".join(parts)


__all__ = [
    "ACTOR",
    "GATE_ACTOR",
    "MONITOR_ACTOR",
    "EvolutionLoop",
    "EvolveResult",
    "FinalEvaluation",
    "PhaseEvaluator",
    "ensure_v0",
    "task_capability_set",
]
