"""Record factories and file helpers shared by the trace tests."""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from capevo.records import CapabilitySet
from capevo.runtime.traces import (
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    Intervention,
    Outcome,
    PlanStep,
    TraceMetadata,
    TraceRecord,
    TraceWriter,
    UnsafeStep,
)
from capevo.runtime.traces.scan import McapScan


def make_metadata(run_id: str = "run-1", **overrides: object) -> TraceMetadata:
    fields: dict[str, object] = {
        "run_id": run_id,
        "task": "Lift",
        "capability_set": CapabilitySet(revision=4, active={"reach": 2, "grasp": 1}),
        "phi_hash": "f" * 64,
        "agent_identity_hash": "a" * 64,
        "seeds": (11, 12),
    }
    fields.update(overrides)
    return TraceMetadata.collect(**fields)  # type: ignore[arg-type]


def f32(values: Iterable[float]) -> tuple[float, ...]:
    """Values rounded to float32, as the runtime produces them."""
    return tuple(np.asarray(list(values), dtype=np.float32).tolist())


def make_env_step(episode: int = 0, step: int = 0, *, obs_dim: int = 50, ecm: str = "reach", **kw: object) -> EnvStep:
    rng = np.random.default_rng(episode * 100_003 + step)
    fields: dict[str, object] = {
        "episode": episode,
        "step": step,
        "ecm": ecm,
        "version": 2,
        "obs": f32(rng.standard_normal(obs_dim)),
        "action": f32(rng.uniform(-1, 1, 7)),
        "reward": float(rng.standard_normal()),
        "next_obs": f32(rng.standard_normal(obs_dim)),
        "terminated": False,
        "truncated": False,
        "is_success": False,
        "key_state": {"arm0_eef_pos": f32(rng.standard_normal(3))},
    }
    fields.update(kw)
    return EnvStep(**fields)  # type: ignore[arg-type]


def one_of_each(episode: int = 0) -> list[TraceRecord]:
    """One record of every topic, with non-default values everywhere."""
    return [
        PlanStep(episode=episode, step=0, ecm="reach", version=2, reason="object is far"),
        EcmInvocation(
            episode=episode,
            step=3,
            ecm="reach",
            version=2,
            input_state=f32((0.1, -2.5, 1e-7)),
            output=(0.25, 0.5),
            duration_s=0.0012,
            outcome=Outcome.OK,
            error=None,
        ),
        EcmInvocation(
            episode=episode,
            step=4,
            ecm="grasp",
            version=1,
            input_state=(1.0,),
            output=None,
            duration_s=2.0,
            outcome=Outcome.TIMEOUT,
            error="took 2.0 s, budget 0.5 s",
        ),
        Intervention(
            episode=episode,
            step=5,
            constraint="workspace_box",
            original_action=(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
            result_action=(0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
            reason="eef would leave the box",
        ),
        Intervention(
            episode=episode,
            step=6,
            constraint="max_force",
            original_action=(0.0,) * 7,
            result_action=None,
            reason="force 120 N > 80 N",
        ),
        make_env_step(episode, 0, terminated=True, is_success=True),
        UnsafeStep(episode=episode, step=0, broken=("box", "force"), reasons=("eef left the box", "31.5 N on bin1")),
        EpisodeSummary(
            episode=episode,
            seed=123,
            success=True,
            total_reward=12.5,
            steps=1,
            interventions=2,
            unsafe_steps=0,
            capability_set={"reach": 2, "grasp": 1},
            duration_s=3.25,
            revision=4,
        ),
    ]


def write_records(writer: TraceWriter, records: Iterable[TraceRecord]) -> None:
    for r in records:
        method = {
            PlanStep: writer.write_plan_step,
            EcmInvocation: writer.write_invocation,
            Intervention: writer.write_intervention,
            EnvStep: writer.write_env_step,
            UnsafeStep: writer.write_unsafe_step,
            EpisodeSummary: writer.write_episode_summary,
        }[type(r)]
        method(r)  # type: ignore[operator]


def write_trace(path: Path, records: Iterable[TraceRecord], **writer_kw: object) -> Path:
    with TraceWriter(path, make_metadata(), **writer_kw) as w:  # type: ignore[arg-type]
        write_records(w, records)
    return path


def count_messages(path: Path) -> int:
    """Messages a lenient scan of ``path`` finds (works while a writer still has it open)."""
    from mcap.records import Message

    return sum(isinstance(r, Message) for r in McapScan(path))


def same_floats(a: Iterable[float], b: Iterable[float], *, ulps: int = 0) -> bool:
    """Equal lengths and values, NaN matching NaN; with ``ulps``, finite values may differ by that
    many float32 ulps (beyond float32's range, by nine significant digits)."""
    a, b = list(a), list(b)
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if x == y or (math.isnan(x) and math.isnan(y)):
            continue
        if not (ulps and math.isfinite(x) and math.isfinite(y)):
            return False
        m = max(abs(x), abs(y))
        tolerance = ulps * float(np.spacing(np.float32(m))) if m < 3.4e38 else m * 1e-8
        if abs(x - y) > tolerance:
            return False
    return True
