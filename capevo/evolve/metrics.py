"""Per-iteration metrics of the closed loop, and the durable files they are appended to.

One :class:`IterationMetrics` row per finished iteration goes to ``metrics.jsonl`` (the record
of truth: canonical JSON, one ``write`` and an ``fsync`` per row) and to ``metrics.csv`` (the
same row's scalar columns, also fsynced). A crash can tear at most the last line of either
file; readers skip a torn JSONL tail, and :meth:`MetricsLog.open` rebuilds the CSV from the
JSONL whenever the two disagree, so a resumed run appends to consistent files.

Invariants:
1. A row whose :meth:`MetricsLog.append` returned is read back equal, even after a SIGKILL.
2. ``metrics.csv`` holds exactly the rows of ``metrics.jsonl``, in order, after
   :meth:`MetricsLog.open`.
3. Iterations in the log are 0, 1, 2, ... without gaps or repeats (``append`` refuses others).
4. :func:`outcome_stats` of an empty list is all zeros with no intervals; otherwise the
   success interval is Wilson's and the reward interval a Student t interval of the mean.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capevo.errors import Corrupt, Invalid
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.storage.blobs import append_synced, fsync_dir

CI_ALPHA = 0.025
"""Each end of the reported intervals is a one-sided 97.5% bound: two-sided 95%."""

CSV_COLUMNS: tuple[str, ...] = (
    "iteration",
    "episodes",
    "successes",
    "success_rate",
    "success_low",
    "success_high",
    "reward_mean",
    "reward_var",
    "reward_low",
    "reward_high",
    "steps_mean",
    "interventions",
    "unsafe_steps",
    "ecm_failures",
    "delta_pi",
    "identity_hash",
    "active_versions",
    "ecm_updated",
    "candidate_version",
    "learner",
    "learner_episodes",
    "learner_steps",
    "gate_decision",
    "gate_n",
    "gate_candidate_success",
    "gate_active_success",
    "gate_p_success",
    "gate_p_noninferiority",
    "gate_p_reward",
    "rollbacks",
    "active_after",
    "wall_live_s",
    "wall_learn_s",
    "wall_gate_s",
    "wall_s",
    "started_at",
)


def is_rollback(action: Mapping[str, Any]) -> bool:
    """A monitor action (:meth:`~capevo.runtime.monitor.MonitorAction.to_dict`) that rolled back or tried to."""
    return bool(action.get("rolled_back") or action.get("error"))


def split_monitor_actions(
    actions: Sequence[Mapping[str, Any]],
) -> tuple[list[Mapping[str, Any]], list[Mapping[str, Any]]]:
    """``(rollbacks, not_confirmed)``: rollbacks (and failed attempts), and drops that the
    replaced version's replay on the same seeds did not confirm."""
    return [a for a in actions if is_rollback(a)], [a for a in actions if not is_rollback(a)]


@dataclass(frozen=True, slots=True, kw_only=True)
class OutcomeStats:
    """Summary of a batch of episodes."""

    episodes: int
    successes: int
    success_rate: float
    success_low: float | None
    success_high: float | None
    reward_mean: float
    reward_var: float
    """Sample variance σ² of the episode returns (0 with fewer than two episodes)."""
    reward_low: float | None
    reward_high: float | None
    steps_mean: float
    interventions: int
    unsafe_steps: int
    ecm_failures: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "episodes": self.episodes,
            "successes": self.successes,
            "success_rate": self.success_rate,
            "success_low": self.success_low,
            "success_high": self.success_high,
            "reward_mean": self.reward_mean,
            "reward_var": self.reward_var,
            "reward_low": self.reward_low,
            "reward_high": self.reward_high,
            "steps_mean": self.steps_mean,
            "interventions": self.interventions,
            "unsafe_steps": self.unsafe_steps,
            "ecm_failures": self.ecm_failures,
        }


def outcome_stats(outcomes: Sequence[EpisodeOutcome]) -> OutcomeStats:
    """Success rate with a 95% Wilson interval, mean reward with a 95% t interval, σ², counts."""
    n = len(outcomes)
    if n == 0:
        return OutcomeStats(
            episodes=0,
            successes=0,
            success_rate=0.0,
            success_low=None,
            success_high=None,
            reward_mean=0.0,
            reward_var=0.0,
            reward_low=None,
            reward_high=None,
            steps_mean=0.0,
            interventions=0,
            unsafe_steps=0,
            ecm_failures=0,
        )
    from scipy import stats as sps

    from capevo.runtime.gate_stats import wilson_interval

    k = sum(1 for o in outcomes if o.success)
    ci = wilson_interval(k, n, alpha=CI_ALPHA)
    rewards = [float(o.reward) for o in outcomes if math.isfinite(o.reward)]
    mean = math.fsum(rewards) / len(rewards) if rewards else 0.0
    var = math.fsum((r - mean) ** 2 for r in rewards) / (len(rewards) - 1) if len(rewards) > 1 else 0.0
    if len(rewards) > 1:
        half = float(sps.t.ppf(1 - CI_ALPHA, len(rewards) - 1)) * math.sqrt(var / len(rewards))
        r_low, r_high = mean - half, mean + half
    else:
        r_low = r_high = None
    return OutcomeStats(
        episodes=n,
        successes=k,
        success_rate=k / n,
        success_low=ci.low,
        success_high=ci.high,
        reward_mean=mean,
        reward_var=var,
        reward_low=r_low,
        reward_high=r_high,
        steps_mean=sum(o.steps for o in outcomes) / n,
        interventions=sum(o.interventions for o in outcomes),
        unsafe_steps=sum(o.unsafe_steps for o in outcomes),
        ecm_failures=sum(o.ecm_failures for o in outcomes),
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class GateSummary:
    """What one iteration's gate decided, in the numbers the report prints."""

    ecm: str
    candidate_version: int
    active_version: int | None
    decision: str
    """``promote`` or ``reject``."""
    mode: str
    n: int
    candidate_successes: int
    candidate_rate: float
    candidate_low: float
    candidate_high: float
    active_successes: int | None = None
    active_rate: float | None = None
    active_low: float | None = None
    active_high: float | None = None
    diff_low: float | None = None
    diff_high: float | None = None
    p_success: float | None = None
    p_noninferiority: float | None = None
    p_reward: float | None = None
    candidate_reward: float | None = None
    active_reward: float | None = None
    failed_checks: tuple[str, ...] = ()
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "ecm": self.ecm,
            "candidate_version": self.candidate_version,
            "active_version": self.active_version,
            "decision": self.decision,
            "mode": self.mode,
            "n": self.n,
            "candidate_successes": self.candidate_successes,
            "candidate_rate": self.candidate_rate,
            "candidate_low": self.candidate_low,
            "candidate_high": self.candidate_high,
            "active_successes": self.active_successes,
            "active_rate": self.active_rate,
            "active_low": self.active_low,
            "active_high": self.active_high,
            "diff_low": self.diff_low,
            "diff_high": self.diff_high,
            "p_success": self.p_success,
            "p_noninferiority": self.p_noninferiority,
            "p_reward": self.p_reward,
            "candidate_reward": self.candidate_reward,
            "active_reward": self.active_reward,
            "failed_checks": list(self.failed_checks),
            "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GateSummary:
        fields = dict(d)
        fields["failed_checks"] = tuple(fields.get("failed_checks") or ())
        return cls(**{k: v for k, v in fields.items() if k in cls.__dataclass_fields__})

    @classmethod
    def from_evidence(cls, evidence: Mapping[str, Any], *, reason: str = "") -> GateSummary:
        """Read a :mod:`capevo.runtime.gate` evidence document (``capevo.gate/1``).

        Raises:
            Invalid: not gate evidence.
        """
        try:
            cand = evidence["candidate"]
            paired = evidence.get("paired")
            active = evidence.get("active")
            checks = evidence.get("checks") or []
            return cls(
                ecm=str(evidence["name"]),
                candidate_version=int(evidence["candidate_version"]),
                active_version=evidence.get("active_version"),
                decision=str(evidence["decision"]),
                mode=str(evidence.get("mode", "paired" if paired else "absolute")),
                n=int(evidence["n"]),
                candidate_successes=int(cand["successes"]),
                candidate_rate=float(cand["success_rate"]),
                candidate_low=float(cand["success_interval"]["low"]),
                candidate_high=float(cand["success_interval"]["high"]),
                active_successes=int(active["successes"]) if active else None,
                active_rate=float(active["success_rate"]) if active else None,
                active_low=float(active["success_interval"]["low"]) if active else None,
                active_high=float(active["success_interval"]["high"]) if active else None,
                diff_low=float(paired["success_difference"]["low"]) if paired else None,
                diff_high=float(paired["success_difference"]["high"]) if paired else None,
                p_success=float(paired["p_success"]) if paired else None,
                p_noninferiority=float(paired["p_noninferiority"]) if paired else None,
                p_reward=float(paired["p_reward"]) if paired else None,
                candidate_reward=float(cand["mean_reward"]),
                active_reward=float(active["mean_reward"]) if active else None,
                failed_checks=tuple(str(c["name"]) for c in checks if not c.get("passed")),
                reason=reason,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise Invalid(f"not gate evidence: {exc}", details={"field": "gate_evidence"}) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class ChainUpdate:
    """A later update of an iteration that learned several ECMs in sequence (a chain)."""

    ecm: str | None
    version: int | None = None
    learner: str | None = None
    gate: GateSummary | None = None
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "ecm": self.ecm,
            "version": self.version,
            "learner": self.learner,
            "gate": self.gate.to_dict() if self.gate is not None else None,
            "note": self.note,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ChainUpdate:
        return cls(
            ecm=d.get("ecm"),
            version=d.get("version"),
            learner=d.get("learner"),
            gate=GateSummary.from_dict(d["gate"]) if d.get("gate") else None,
            note=str(d.get("note") or ""),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class IterationMetrics:
    """One finished closed-loop iteration."""

    iteration: int
    started_at: float
    live: OutcomeStats
    live_seeds: tuple[int, ...]
    episodes: tuple[Mapping[str, Any], ...]
    """Per live episode: seed, success, reward, steps, interventions, unsafe_steps, trace."""
    delta_pi: float
    identity_hash: str
    active_versions: Mapping[str, int]
    """The capability set the live episodes ran."""
    active_after: Mapping[str, int]
    """The capability set at the end of the iteration (after promotion or rollback)."""
    ecm_updated: str | None = None
    candidate_version: int | None = None
    learner: str | None = None
    learner_episodes: int = 0
    learner_steps: int = 0
    """Env steps of the learners' training episodes (see :attr:`capevo.evolve.learners.Proposal.steps`)."""
    env_steps_live: int = 0
    """Env steps of the iteration's live episodes."""
    env_steps_gate: int = 0
    """Env steps of the iteration's gate episodes (both sides of every pair)."""
    env_steps_monitor: int = 0
    """Env steps of the degradation monitor's confirmation episodes (the replaced version
    replayed on a live window's seeds; see :mod:`capevo.runtime.monitor`)."""
    gate: GateSummary | None = None
    further: tuple[ChainUpdate, ...] = ()
    """The chain's later updates, when the iteration learned several ECMs (``ecm_updated``,
    ``candidate_version`` and ``gate`` are the first one's)."""
    update_note: str = ""
    """Why there was no candidate (no failures, learner error, ...), or where it came from."""
    rollbacks: tuple[Mapping[str, Any], ...] = ()
    """Every action of the degradation monitor (:meth:`~capevo.runtime.monitor.MonitorAction.to_dict`):
    rollbacks, failed rollbacks (``error``) and firings not confirmed on the same seeds."""
    wall_live_s: float = 0.0
    wall_learn_s: float = 0.0
    wall_gate_s: float = 0.0
    wall_s: float = 0.0
    traces: tuple[str, ...] = field(default_factory=tuple)

    @property
    def env_steps(self) -> int:
        """Every env step the iteration spent: live, monitor, learner and gate episodes (issue 20's budget)."""
        return self.env_steps_live + self.env_steps_monitor + self.learner_steps + self.env_steps_gate

    @property
    def gate_decision(self) -> str:
        return self.gate.decision if self.gate is not None else "none"

    @property
    def gates(self) -> tuple[GateSummary, ...]:
        """Every gate decision of the iteration, in order (the first update's, then the chain's)."""
        first = (self.gate,) if self.gate is not None else ()
        return first + tuple(u.gate for u in self.further if u.gate is not None)

    def to_dict(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration,
            "started_at": self.started_at,
            "live": self.live.to_dict(),
            "live_seeds": list(self.live_seeds),
            "episodes": [dict(e) for e in self.episodes],
            "delta_pi": self.delta_pi,
            "identity_hash": self.identity_hash,
            "active_versions": dict(self.active_versions),
            "active_after": dict(self.active_after),
            "ecm_updated": self.ecm_updated,
            "candidate_version": self.candidate_version,
            "learner": self.learner,
            "learner_episodes": self.learner_episodes,
            "learner_steps": self.learner_steps,
            "env_steps_live": self.env_steps_live,
            "env_steps_gate": self.env_steps_gate,
            "env_steps_monitor": self.env_steps_monitor,
            "gate": self.gate.to_dict() if self.gate is not None else None,
            "further": [u.to_dict() for u in self.further],
            "update_note": self.update_note,
            "rollbacks": [dict(r) for r in self.rollbacks],
            "wall_live_s": self.wall_live_s,
            "wall_learn_s": self.wall_learn_s,
            "wall_gate_s": self.wall_gate_s,
            "wall_s": self.wall_s,
            "traces": list(self.traces),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IterationMetrics:
        """Inverse of :meth:`to_dict`.

        Raises:
            Invalid: a missing or bad field.
        """
        try:
            return cls(
                iteration=int(d["iteration"]),
                started_at=float(d["started_at"]),
                live=OutcomeStats(**d["live"]),
                live_seeds=tuple(int(s) for s in d["live_seeds"]),
                episodes=tuple(dict(e) for e in d.get("episodes") or ()),
                delta_pi=float(d["delta_pi"]),
                identity_hash=str(d["identity_hash"]),
                active_versions={str(k): int(v) for k, v in d["active_versions"].items()},
                active_after={str(k): int(v) for k, v in d["active_after"].items()},
                ecm_updated=d.get("ecm_updated"),
                candidate_version=d.get("candidate_version"),
                learner=d.get("learner"),
                learner_episodes=int(d.get("learner_episodes") or 0),
                learner_steps=int(d.get("learner_steps") or 0),
                env_steps_live=int(d.get("env_steps_live") or 0),
                env_steps_gate=int(d.get("env_steps_gate") or 0),
                env_steps_monitor=int(d.get("env_steps_monitor") or 0),
                gate=GateSummary.from_dict(d["gate"]) if d.get("gate") else None,
                further=tuple(ChainUpdate.from_dict(u) for u in d.get("further") or ()),
                update_note=str(d.get("update_note") or ""),
                rollbacks=tuple(dict(r) for r in d.get("rollbacks") or ()),
                wall_live_s=float(d.get("wall_live_s") or 0.0),
                wall_learn_s=float(d.get("wall_learn_s") or 0.0),
                wall_gate_s=float(d.get("wall_gate_s") or 0.0),
                wall_s=float(d.get("wall_s") or 0.0),
                traces=tuple(str(t) for t in d.get("traces") or ()),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise Invalid(f"bad metrics row: {exc}", details={"field": "metrics"}) from None

    def csv_row(self) -> dict[str, Any]:
        """The scalar columns of :data:`CSV_COLUMNS`."""
        g = self.gate
        return {
            "iteration": self.iteration,
            "episodes": self.live.episodes,
            "successes": self.live.successes,
            "success_rate": _num(self.live.success_rate),
            "success_low": _num(self.live.success_low),
            "success_high": _num(self.live.success_high),
            "reward_mean": _num(self.live.reward_mean),
            "reward_var": _num(self.live.reward_var),
            "reward_low": _num(self.live.reward_low),
            "reward_high": _num(self.live.reward_high),
            "steps_mean": _num(self.live.steps_mean),
            "interventions": self.live.interventions,
            "unsafe_steps": self.live.unsafe_steps,
            "ecm_failures": self.live.ecm_failures,
            "delta_pi": _num(self.delta_pi),
            "identity_hash": self.identity_hash,
            "active_versions": _versions(self.active_versions),
            "ecm_updated": self.ecm_updated or "",
            "candidate_version": "" if self.candidate_version is None else self.candidate_version,
            "learner": self.learner or "",
            "learner_episodes": self.learner_episodes,
            "learner_steps": self.learner_steps,
            "gate_decision": self.gate_decision,
            "gate_n": g.n if g else "",
            "gate_candidate_success": _num(g.candidate_rate) if g else "",
            "gate_active_success": _num(g.active_rate) if g else "",
            "gate_p_success": _num(g.p_success) if g else "",
            "gate_p_noninferiority": _num(g.p_noninferiority) if g else "",
            "gate_p_reward": _num(g.p_reward) if g else "",
            "rollbacks": ";".join(
                f"{r.get('name')}@{r.get('version')}->{r.get('to_version')}" for r in self.rollbacks if is_rollback(r)
            ),
            "active_after": _versions(self.active_after),
            "wall_live_s": _num(self.wall_live_s),
            "wall_learn_s": _num(self.wall_learn_s),
            "wall_gate_s": _num(self.wall_gate_s),
            "wall_s": _num(self.wall_s),
            "started_at": _num(self.started_at),
        }


def _num(x: float | None) -> str:
    return "" if x is None else f"{x:.6g}"


def _versions(v: Mapping[str, int]) -> str:
    return " ".join(f"{k}@{n}" for k, n in sorted(v.items()))


# --- durable files ----------------------------------------------------------------------


def append_durably(path: Path, data: bytes) -> None:
    """Append ``data`` with one write and fsync it (and the directory when the file is new).

    A failed write is cut off again so no half line is left for the next append.

    Raises:
        Invalid: the file cannot be written.
    """
    new = not path.exists()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
    except OSError as exc:
        raise Invalid(f"cannot open {path}: {exc.strerror}", details={"path": str(path)}) from None
    try:
        try:
            append_synced(fd, data)
        except OSError as exc:
            raise Invalid(f"cannot append to {path}: {exc.strerror}", details={"path": str(path)}) from None
    finally:
        os.close(fd)
    if new:
        fsync_dir(path.parent)


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data``: write a temporary file, fsync, rename, fsync the directory."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def read_jsonl(path: Path) -> tuple[list[dict[str, Any]], int]:
    """Complete JSON lines of ``path`` and the length of a torn (unterminated) last line.

    Raises:
        Corrupt: a complete line that is not a JSON object.
    """
    if not path.exists():
        return [], 0
    data = path.read_bytes()
    out: list[dict[str, Any]] = []
    lines = data.split(b"\n")
    torn = len(lines[-1])
    for lineno, raw in enumerate(lines[:-1], start=1):
        if not raw.strip():
            continue
        try:
            value = json.loads(raw)
        except ValueError as exc:
            raise Corrupt(f"{path}:{lineno}: not JSON: {exc}", details={"path": str(path), "line": lineno}) from None
        if not isinstance(value, dict):
            raise Corrupt(f"{path}:{lineno}: not a JSON object", details={"path": str(path), "line": lineno})
        out.append(value)
    return out, torn


def repair_jsonl(path: Path) -> list[dict[str, Any]]:
    """:func:`read_jsonl`, then cut a torn last line off the file (it was never acknowledged), so
    the next append starts on a fresh line."""
    rows, torn = read_jsonl(path)
    if torn:
        size = path.stat().st_size
        with open(path, "r+b") as f:
            f.truncate(size - torn)
            f.flush()
            os.fsync(f.fileno())
    return rows


def canonical_line(value: Mapping[str, Any]) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False).encode() + b"\n"


class MetricsLog:
    """``metrics.jsonl`` + ``metrics.csv`` in ``directory``, opened for appending.

    Args:
        directory: The report directory (created if absent).

    Raises:
        Corrupt: a malformed row that is not the torn tail, or iterations out of order.
    """

    JSONL = "metrics.jsonl"
    CSV = "metrics.csv"

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.jsonl_path = self.directory / self.JSONL
        self.csv_path = self.directory / self.CSV
        rows = repair_jsonl(self.jsonl_path)
        self._rows = [IterationMetrics.from_dict(r) for r in rows]
        for i, row in enumerate(self._rows):
            if row.iteration != i:
                raise Corrupt(
                    f"{self.jsonl_path}: row {i + 1} is iteration {row.iteration}, expected {i}",
                    details={"path": str(self.jsonl_path)},
                )
        if self._csv_text(self._rows) != (self.csv_path.read_text() if self.csv_path.exists() else None):
            write_atomically(self.csv_path, self._csv_text(self._rows).encode())

    @staticmethod
    def _csv_text(rows: Sequence[IterationMetrics]) -> str:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=list(CSV_COLUMNS), lineterminator="\n")
        writer.writeheader()
        for r in rows:
            writer.writerow(r.csv_row())
        return buf.getvalue()

    @property
    def rows(self) -> tuple[IterationMetrics, ...]:
        return tuple(self._rows)

    @property
    def completed(self) -> int:
        """Number of finished iterations (the next iteration's index)."""
        return len(self._rows)

    def append(self, row: IterationMetrics) -> None:
        """Append one finished iteration to both files, durably.

        Raises:
            Invalid: ``row.iteration`` is not the next iteration.
        """
        if row.iteration != len(self._rows):
            raise Invalid(
                f"metrics row for iteration {row.iteration}, expected {len(self._rows)}", details={"field": "iteration"}
            )
        append_durably(self.jsonl_path, canonical_line(row.to_dict()))
        buf = io.StringIO()
        csv.DictWriter(buf, fieldnames=list(CSV_COLUMNS), lineterminator="\n").writerow(row.csv_row())
        append_durably(self.csv_path, buf.getvalue().encode())
        self._rows.append(row)


def read_metrics(directory: str | os.PathLike[str]) -> list[IterationMetrics]:
    """The finished iterations recorded in ``directory`` (read only; a torn tail is skipped)."""
    rows, _ = read_jsonl(Path(directory) / MetricsLog.JSONL)
    return [IterationMetrics.from_dict(r) for r in rows]


__all__ = [
    "CSV_COLUMNS",
    "ChainUpdate",
    "GateSummary",
    "IterationMetrics",
    "MetricsLog",
    "OutcomeStats",
    "append_durably",
    "canonical_line",
    "is_rollback",
    "outcome_stats",
    "read_jsonl",
    "read_metrics",
    "repair_jsonl",
    "split_monitor_actions",
    "write_atomically",
]
