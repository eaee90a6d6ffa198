"""LLM code synthesis: ask a chat model to edit a code ECM, and accept only code that is safe
and runs.

For one :class:`~capevo.learner.base.LearnRequest` the learner

1. builds a prompt from the code ECM contract, the ECM's descriptor φ (description,
   applicability and termination over the task's signals), its interface, a summary of recent
   failures read from the traces, and the current source;
2. calls the chat endpoint and extracts the reply's Python code block;
3. validates it with the sandbox validator *before anything runs* (a rule break raises
   :class:`SandboxViolation`) and reads its ``PARAMS`` literal;
4. smoke-runs it in a sandbox worker process on real inputs from the traces (or neutral
   ones): ``done`` and ``act`` must return an action of the task's dimension, all finite;
5. on a rejection, tells the model why and asks again, up to ``max_attempts`` replies;
6. returns a :class:`Candidate` with origin ``llm``.

Without a configured endpoint (``chat=None``, e.g. ``CAPEVO_LLM_BASE_URL`` unset) it logs a
warning and delegates to ``fallback`` (normally :class:`~capevo.learner.search.CemSearch`);
the candidate then carries the fallback's origin and ``notes["fallback"]``.

Invariants:
1. Code from the model is executed only after :func:`validate_source` accepted it. The smoke
   run is always in a sandbox worker; scoring episodes run it as origin ``llm`` under the
   evaluator's trust policy (sandboxed by default).
2. A returned candidate's source passed validation and the smoke run.
3. When every attempt is rejected, the last rejection is raised (:class:`SandboxViolation`
   for a rule break, :class:`Invalid` otherwise); no candidate is returned.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from capevo.errors import CapevoError, Invalid, SandboxViolation, Unavailable
from capevo.learner.base import Candidate, CandidateEvaluator, Learner, LearnRequest, Score, config_hash, score_outcomes
from capevo.learner.chat import Chat
from capevo.learner.experience import EpisodeEnd, episode_ends, failure_summary, trace_paths
from capevo.learner.search import candidate_spec
from capevo.records import Interface, IOSpec, Origin, Predicate, Provenance
from capevo.runtime.ecm.code import read_params
from capevo.runtime.ecm.marshal import output_size
from capevo.runtime.sandbox import SandboxConfig, SandboxedSkill, validate_source
from capevo.runtime.sandbox.client import SkillRaised, WorkerDied

log = logging.getLogger(__name__)

PROMPT_VERSION = "1"
"""Bump when the prompt changes meaningfully (it is part of the config hash)."""

SYSTEM_PROMPT = """You improve robot manipulation skills. Each skill (a "code ECM") is one \
small, self-contained Python module that a runtime calls once per control step.

The contract:
- PARAMS = {...}: a literal dict of str -> number at module level (tunable parameters).
- def act(obs, params): returns the action, a flat list of floats (its length is given below), \
each in [-1, 1]. obs is a dict of read-only numpy arrays keyed by the input names given below; \
params is a read-only mapping (PARAMS, possibly with other values).
- def done(obs, params): optional; True ends the skill early.
- act and done must be pure functions of their arguments: keep no state between calls.
- Only `import math` and `import numpy as np` are allowed. No classes, no file or network \
access, no open/exec/eval/compile/getattr, no names or attributes starting with an underscore, \
no str.format.
- Observations are noisy (about 1 cm Gaussian noise per step on positions) and some actions are \
dropped; write robust logic (tolerances, hysteresis read from the state, gripper commands that \
hold their state).

Reply with the complete new module in a single ```python fenced code block and nothing else."""


def _predicate_text(p: Predicate) -> str:
    conds = " and ".join(f"{c.signal} {c.op} {c.value:g}" for c in p.all)
    if p.text and conds:
        return f"{p.text} ({conds})"
    return p.text or conds or "always"


def _interface_text(interface: Interface) -> str:
    def spec(s: IOSpec) -> str:
        bounds = f" in [{s.low:g}, {s.high:g}]" if s.low is not None and s.high is not None else ""
        units = f" {s.units}" if s.units else ""
        return f"{s.name}: shape {list(s.shape)} {s.dtype}{units}{bounds}"

    ins = "\n".join("  - " + spec(s) for s in interface.inputs) or "  - (the whole raw observation)"
    outs = "\n".join("  - " + spec(s) for s in interface.outputs) or "  - action"
    return f"Inputs (obs keys):\n{ins}\nOutputs (the action):\n{outs}"


def build_messages(request: LearnRequest, *, failures: str) -> list[dict[str, str]]:
    """The chat messages asking for an improved version of ``request.ecm``."""
    p = request.parent
    d = p.descriptor
    user = (
        f"Task: {request.task}. Plan: {' -> '.join(request.decomposition)}.\n"
        f"Skill to improve: {request.ecm} (version {p.version}).\n"
        f"What it does: {d.description}\n"
        f"It runs when: {_predicate_text(d.applicability)}\n"
        f"It is done (checked by the runtime on exact simulator signals before each call): "
        f"{_predicate_text(d.termination)}\n"
        f"{_interface_text(p.interface)}\n\n"
        f"Recent experience:\n{failures}\n\n"
        f"Current source:\n```python\n{request.source}\n```\n\n"
        "Change the code so that the skill reaches its termination condition reliably and quickly "
        "under the noise. Keep the PARAMS literal (you may change, add or remove entries)."
    )
    return [{"role": "system", "content": SYSTEM_PROMPT}, {"role": "user", "content": user}]


_FENCE = re.compile(r"```[ \t]*(?:python|py|python3)?[ \t]*\r?\n(.*?)```", re.DOTALL | re.IGNORECASE)


def extract_code(reply: str) -> str:
    """The Python module in a model's reply: the longest fenced block, else the whole text if it
    defines ``act``.

    Raises:
        Invalid: no code in the reply.
    """
    blocks = [b for b in _FENCE.findall(reply) if b.strip()]
    if blocks:
        return max(blocks, key=len).strip() + "\n"
    if re.search(r"^def act\(", reply, re.MULTILINE):
        return reply.strip() + "\n"
    raise Invalid("the reply holds no Python code block", details={"field": "reply"})


def _neutral_input(spec: IOSpec) -> np.ndarray:
    arr = np.zeros(spec.shape, dtype=spec.dtype)
    if spec.name.endswith("quat") and arr.shape == (4,):
        arr[0] = 1.0  # the Panda's hand pointing down (x, y, z, w)
    return arr


def smoke_inputs(interface: Interface, ends: Sequence[EpisodeEnd], ecm: str, *, limit: int = 3) -> list[dict]:
    """Inputs for a smoke run: the ECM's last real inputs from the traces, else neutral ones."""
    out: list[dict[str, np.ndarray]] = []
    sizes = [math.prod(s.shape) for s in interface.inputs]
    for end in ends:
        flat = end.last_inputs.get(ecm)
        if flat is None or len(flat) != sum(sizes):
            continue
        at, sample = 0, {}
        for s, n in zip(interface.inputs, sizes, strict=True):
            sample[s.name] = np.asarray(flat[at : at + n], dtype=s.dtype).reshape(s.shape)
            at += n
        out.append(sample)
        if len(out) >= limit:
            break
    if not out:
        out.append({s.name: _neutral_input(s) for s in interface.inputs})
    return out


def smoke_run(
    source: str,
    interface: Interface,
    samples: Sequence[Mapping[str, np.ndarray]],
    *,
    action_dim: int,
    sandbox: SandboxConfig | None = None,
    timeout_s: float = 2.0,
    filename: str = "<candidate>",
) -> None:
    """Run ``done`` and ``act`` on each sample in a sandbox worker.

    Raises:
        SandboxViolation: the source breaks a validation rule (nothing ran).
        Invalid: it does not load, raises, times out, or returns a bad action.
    """
    try:
        skill = SandboxedSkill(source, config=sandbox, filename=filename)
    except WorkerDied as exc:
        raise Invalid(f"{filename}: the sandbox worker could not start the skill: {exc}") from None
    try:
        for sample in samples:
            try:
                step = skill.step(sample, timeout_s=timeout_s)
            except (SkillRaised, WorkerDied) as exc:
                raise Invalid(f"{filename}: smoke run failed: {exc}") from None
            except CapevoError as exc:  # Timeout
                raise Invalid(f"{filename}: smoke run failed: {exc.message}") from None
            except Exception as exc:  # BadOutput
                raise Invalid(f"{filename}: smoke run failed: {type(exc).__name__}: {exc}") from None
            if step.done:
                continue
            action = step.action
            if action is None or action.shape != (action_dim,):
                got = None if action is None else list(action.shape)
                raise Invalid(f"{filename}: act returned shape {got}, expected [{action_dim}]")
            if not bool(np.all(np.isfinite(action))):
                raise Invalid(f"{filename}: act returned non-finite values")
    finally:
        skill.close()


def check_source(
    source: str,
    request: LearnRequest,
    *,
    ends: Sequence[EpisodeEnd] = (),
    sandbox: SandboxConfig | None = None,
) -> dict[str, float]:
    """Validate, read ``PARAMS`` and smoke-run a proposed source for ``request.ecm``.

    Returns:
        The source's ``PARAMS``.

    Raises:
        SandboxViolation: a validation rule is broken (checked before anything runs).
        Invalid: syntax, ``PARAMS`` or contract errors, or a failed smoke run.
    """
    filename = f"<{request.ecm} candidate>"
    validate_source(source, filename=filename)
    params = read_params(source, filename=filename)
    interface = request.parent.interface
    dim = output_size(interface.outputs) if interface.outputs else None
    if dim is None:
        from capevo.runtime.tasks import task_spec

        dim = task_spec(request.task).action_layout.dim
    smoke_run(
        source,
        interface,
        smoke_inputs(interface, ends, request.ecm),
        action_dim=dim,
        sandbox=sandbox,
        filename=filename,
    )
    return params


@dataclass(frozen=True, slots=True, kw_only=True)
class Attempt:
    """One reply of the model and what became of it."""

    reply_chars: int
    accepted: bool
    error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"reply_chars": self.reply_chars, "accepted": self.accepted, "error": self.error}


class LlmSynthesis:
    """Learner: a chat model edits the ECM's code (see the module docstring).

    Args:
        chat: The endpoint; None means none is configured (use ``fallback``).
        fallback: Learner used without an endpoint (normally a :class:`CemSearch`).
        max_attempts: Model replies tried per request (each rejection is fed back).
        evaluator: When given, the accepted candidate and its parent are scored on the
            request's training seeds (``Candidate.score`` / ``baseline``).
        episodes: Training episodes for that scoring.
        sandbox: Sandbox settings for smoke runs and evaluation.
        origin: Origin of the candidates (``llm``).
        learner_id: Recorded in provenance; default ``llm:<model>``.

    Raises:
        Invalid: ``max_attempts`` or ``episodes`` below 1.
    """

    def __init__(
        self,
        chat: Chat | None,
        *,
        fallback: Learner | None = None,
        max_attempts: int = 2,
        evaluator: CandidateEvaluator | None = None,
        episodes: int = 4,
        sandbox: SandboxConfig | None = None,
        origin: Origin = Origin.LLM,
        learner_id: str | None = None,
    ) -> None:
        if max_attempts < 1 or episodes < 1:
            raise Invalid("max_attempts and episodes must be >= 1", details={"field": "max_attempts"})
        self.chat = chat
        self.fallback = fallback
        self.max_attempts = max_attempts
        self.evaluator = evaluator
        self.episodes = episodes
        self.sandbox = sandbox
        self.origin = Origin(origin)
        self.learner_id = learner_id or (f"llm:{chat.config.model}" if chat is not None else "llm")

    def config(self) -> dict[str, Any]:
        """What shapes this learner's output (hashed into provenance)."""
        return {
            "method": "llm",
            "prompt_version": PROMPT_VERSION,
            "chat": self.chat.config.to_dict() if self.chat is not None else None,
            "max_attempts": self.max_attempts,
        }

    def propose_source(self, request: LearnRequest) -> tuple[str, tuple[Attempt, ...]]:
        """Ask the model until a reply passes :func:`check_source`.

        Returns:
            The accepted source and every attempt.

        Raises:
            Unavailable: no endpoint configured.
            Timeout, Unavailable, Invalid: the endpoint failed.
            SandboxViolation, Invalid: every reply was rejected (the last rejection).
        """
        if self.chat is None:
            raise Unavailable("no chat endpoint is configured (set CAPEVO_LLM_BASE_URL and CAPEVO_LLM_MODEL)")
        ends = episode_ends(request.outcomes)
        summary = failure_summary(ends, request.decomposition, request.ecm)
        messages = build_messages(request, failures=summary)
        attempts: list[Attempt] = []
        last: CapevoError | None = None
        for i in range(self.max_attempts):
            reply = self.chat.complete(messages)
            try:
                source = extract_code(reply)
                check_source(source, request, ends=ends, sandbox=self.sandbox)
            except (SandboxViolation, Invalid) as exc:
                last = exc
                attempts.append(Attempt(reply_chars=len(reply), accepted=False, error=str(exc)[:2000]))
                log.warning("llm reply %d for %s rejected: %s", i + 1, request.ecm, exc)
                messages = [
                    *messages,
                    {"role": "assistant", "content": reply},
                    {
                        "role": "user",
                        "content": f"That module was rejected: {exc.message}\nReply with a corrected complete "
                        "module in one ```python block.",
                    },
                ]
                continue
            attempts.append(Attempt(reply_chars=len(reply), accepted=True))
            return source, tuple(attempts)
        if last is None:  # pragma: no cover - max_attempts >= 1 always tries once
            raise Invalid("no attempt was made")
        raise last

    def _score(self, request: LearnRequest, source: str | None) -> Score | None:
        if self.evaluator is None or not request.train_seeds:
            return None
        seeds = [request.train_seeds[i % len(request.train_seeds)] for i in range(self.episodes)]
        overrides = {request.ecm: source.encode()} if source is not None else None
        outcomes = self.evaluator.evaluate(
            request.task, request.versions, seeds, overrides=overrides, override_origin=self.origin
        )
        return score_outcomes(outcomes, request.decomposition)

    def learn(self, request: LearnRequest) -> Candidate:
        """Propose an LLM-edited version of ``request.ecm`` (or the fallback's candidate).

        Raises:
            Unavailable: no endpoint and no fallback.
            SandboxViolation, Invalid, Timeout, Unavailable: as :meth:`propose_source`.
        """
        if self.chat is None:
            if self.fallback is None:
                raise Unavailable("no chat endpoint is configured and no fallback learner was given")
            log.warning(
                "no chat endpoint configured (CAPEVO_LLM_BASE_URL unset): falling back to %s for %s",
                self.fallback.learner_id,
                request.ecm,
            )
            return self.fallback.learn(request).with_notes(
                fallback=f"no chat endpoint; used {self.fallback.learner_id}"
            )
        source, attempts = self.propose_source(request)
        provenance = Provenance(
            learner_id=self.learner_id,
            config_hash=config_hash({**self.config(), "task": request.task, "ecm": request.ecm}),
            traces=trace_paths(request.outcomes),
        )
        return Candidate(
            ecm=request.ecm,
            artifact=source.encode(),
            spec=candidate_spec(request, origin=self.origin, provenance=provenance),
            score=self._score(request, source),
            baseline=self._score(request, None),
            notes={"learner": self.learner_id, "attempts": [a.to_dict() for a in attempts]},
        )
