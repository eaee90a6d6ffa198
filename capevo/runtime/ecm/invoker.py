"""Step-by-step execution of one ECM with timeouts, a step budget and recovery.

Each :meth:`EcmInvoker.step` marshals the ECM's inputs from the raw observation, calls the
ECM once, classifies the call into an :class:`Outcome`, and on failure lets the recovery
strategy decide (retry, fall back, hold still). The caller gets a :class:`StepResult`
whose ``action`` is what to apply, or None when the skill is over.

How the per-call timeout is enforced:

* sandboxed code (untrusted origins): the host waits at most ``timeout_s`` for the
  worker's reply, then SIGKILLs the worker and starts a replacement; the call is a
  ``timeout``. The kernel's per-call CPU limit backs this up.
* in-process ECMs (trusted code, neural policies): a running Python or torch call cannot
  be interrupted from the same thread, so the invoker measures the call and treats an
  overrun as a ``timeout`` after the fact, discarding its action. A trusted ECM that never
  returns blocks the caller; that is why untrusted code never runs in-process.

Invariants:
1. Nothing an ECM does (raise, hang past the timeout in the sandbox, return NaN/inf, a
   wrong shape or a non-number) propagates out of :meth:`step`; only :class:`Invalid` for
   an observation that does not match the ECM's interface (a wiring error) does.
2. ``step`` never calls the ECM once ``step_budget`` steps were taken since the last
   :meth:`reset`; it returns ``budget_exhausted`` instead.
3. A returned action always has ``layout.dim`` finite values within the interface's
   output bounds (when ``clip_to_bounds``); the safe hold is zeros with each gripper
   command equal to the last action this invoker returned (``default_gripper`` before any).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from capevo.errors import Invalid, Timeout
from capevo.records import Kind
from capevo.runtime.ecm.base import LoadedEcm
from capevo.runtime.ecm.marshal import clip_to_bounds, marshal_inputs, output_size
from capevo.runtime.ecm.outcome import FAILURES, Outcome, Status, StepResult
from capevo.runtime.ecm.recovery import RecoveryStrategy, SafeAbort
from capevo.runtime.sandbox.namespace import BadOutput
from capevo.runtime.state import SINGLE_PANDA, ActionLayout

MAX_ERROR_CHARS = 2000


def _error_text(exc: BaseException) -> str:
    try:
        text = f"{type(exc).__name__}: {exc}"
    except Exception:
        text = type(exc).__name__
    return text[:MAX_ERROR_CHARS]


def raw_observation(obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Every numeric entry of an observation as a read-only array (for code ECMs that
    declare no inputs)."""
    out: dict[str, np.ndarray] = {}
    for key, value in obs.items():
        try:
            arr = np.asarray(value)
        except (TypeError, ValueError):
            continue
        if arr.dtype.kind in "biuf":
            view = arr.view()
            view.flags.writeable = False
            out[str(key)] = view
    return out


class EcmInvoker:
    """Runs one ECM for one activation (one skill execution), step by step.

    Args:
        ecm: The primary ECM (neural or code).
        layout: The task's action layout: action dim and gripper indices for the safe hold.
        timeout_s: Per-call compute limit.
        step_budget: Steps allowed per activation; None for unlimited.
        recovery: What to do on a failed call; default :class:`SafeAbort`.
        clip_to_bounds: Clip actions to the interface's output bounds.
        default_gripper: Gripper command of the safe hold before any action was returned.
        clock: Seconds counter for call durations.

    Raises:
        Invalid: a prompt ECM, non-positive limits, or an ECM whose outputs do not match
            ``layout.dim``.
    """

    def __init__(
        self,
        ecm: LoadedEcm,
        *,
        layout: ActionLayout = SINGLE_PANDA,
        timeout_s: float = 0.5,
        step_budget: int | None = 1000,
        recovery: RecoveryStrategy | None = None,
        clip_to_bounds: bool = True,
        default_gripper: float = 0.0,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        if not timeout_s > 0:
            raise Invalid(f"timeout_s must be positive, got {timeout_s}")
        if step_budget is not None and step_budget < 1:
            raise Invalid(f"step_budget must be >= 1 or None, got {step_budget}")
        self.layout = layout
        self.timeout_s = float(timeout_s)
        self.step_budget = step_budget
        self.recovery = recovery or SafeAbort()
        self.clip = clip_to_bounds
        self._clock = clock
        self._default_gripper = float(default_gripper)
        for e in (ecm, *self.recovery.alternatives()):
            self._check_executable(e)
        self._initial = ecm
        self._primary = ecm
        self._steps_used = 0
        self._step_index = 0
        self._gripper = self._initial_gripper()

    def _check_executable(self, ecm: LoadedEcm) -> None:
        if ecm.runner is None or ecm.kind is Kind.PROMPT:
            raise Invalid(f"{ecm.label}: {ecm.kind.value} ECMs are not executable step by step")
        outputs = ecm.interface.outputs
        if outputs and output_size(outputs) != self.layout.dim:
            raise Invalid(
                f"{ecm.label}: interface outputs total {output_size(outputs)} values, but the task's "
                f"action has {self.layout.dim}",
                details={"field": "interface.outputs", "expected": self.layout.dim, "got": output_size(outputs)},
            )

    def _initial_gripper(self) -> dict[int, float]:
        return {arm.gripper: self._default_gripper for arm in self.layout.arms if arm.gripper is not None}

    # --- state -----------------------------------------------------------------------

    @property
    def primary(self) -> LoadedEcm:
        """The ECM called first each step (changes after a sticky fallback)."""
        return self._primary

    @property
    def steps_used(self) -> int:
        return self._steps_used

    def reset(self) -> None:
        """Start a new activation: budget, step index, gripper memory and primary reset."""
        self._primary = self._initial
        self._steps_used = 0
        self._step_index = 0
        self._gripper = self._initial_gripper()

    def safe_action(self) -> tuple[float, ...]:
        """Zero motion of the task's action dim, each gripper command unchanged."""
        action = [0.0] * self.layout.dim
        for index, value in self._gripper.items():
            action[index] = value
        return tuple(action)

    # --- calls -----------------------------------------------------------------------

    def call(self, ecm: LoadedEcm, obs: Mapping[str, Any]) -> Outcome:
        """Call ``ecm`` once on ``obs`` and classify the result (no budget, no recovery).

        Raises:
            Invalid: ``obs`` does not provide the ECM's declared inputs.
        """
        if ecm.runner is None:
            raise Invalid(f"{ecm.label}: not executable")
        interface = ecm.interface
        inputs = marshal_inputs(obs, interface.inputs, ecm=ecm.label) if interface.inputs else raw_observation(obs)
        clock = self._clock
        t0 = clock()
        try:
            result = ecm.runner.step(inputs, timeout_s=self.timeout_s)
        except Timeout as exc:
            return self._outcome(ecm, Status.TIMEOUT, t0, error=exc.message)
        except BadOutput as exc:
            return self._outcome(ecm, Status.BAD_SHAPE, t0, error=str(exc)[:MAX_ERROR_CHARS])
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # an ECM may raise anything, even SystemExit
            return self._outcome(ecm, Status.EXCEPTION, t0, error=_error_text(exc))
        elapsed = clock() - t0
        if ecm.in_process and elapsed > self.timeout_s:
            return self._outcome(
                ecm,
                Status.TIMEOUT,
                t0,
                error=f"in-process call took {elapsed:.3f}s, over the {self.timeout_s}s limit; result discarded",
            )
        if result.done:
            return self._outcome(ecm, Status.TERMINATED, t0)
        raw = result.action
        if raw is None or raw.shape != (self.layout.dim,):
            got = None if raw is None else raw.shape
            return self._outcome(
                ecm, Status.BAD_SHAPE, t0, error=f"action has shape {got}, expected ({self.layout.dim},)"
            )
        if not np.isfinite(raw).all():
            return self._outcome(ecm, Status.NAN, t0, error=f"action has non-finite values: {raw.tolist()}")
        action = raw
        clipped = False
        if self.clip and interface.outputs:
            action, clipped = clip_to_bounds(raw, interface.outputs)
        values = action.tolist()
        if action.dtype.kind != "f":  # tolist() gives Python floats only for float arrays
            values = [float(x) for x in values]
        return self._outcome(ecm, Status.OK, t0, action=tuple(values), clipped=clipped)

    def _outcome(
        self,
        ecm: LoadedEcm,
        status: Status,
        started: float,
        *,
        action: tuple[float, ...] | None = None,
        error: str | None = None,
        clipped: bool = False,
    ) -> Outcome:
        return Outcome(
            status=status,
            ecm=ecm.name,
            version=ecm.version,
            action=action,
            duration_s=self._clock() - started,
            error=error,
            clipped=clipped,
        )

    def step(self, obs: Mapping[str, Any]) -> StepResult:
        """Advance the ECM by one step.

        Args:
            obs: The environment's raw observation dict.

        Returns:
            The step's result; ``action`` None means the skill is over.

        Raises:
            Invalid: ``obs`` does not provide the ECM's declared inputs.
        """
        index = self._step_index
        self._step_index += 1
        if self.step_budget is not None and self._steps_used >= self.step_budget:
            skipped = Outcome(
                status=Status.BUDGET_EXHAUSTED,
                ecm=self._primary.name,
                version=self._primary.version,
                action=None,
                duration_s=0.0,
                error=f"step budget of {self.step_budget} used up",
            )
            return StepResult(step=index, status=Status.BUDGET_EXHAUSTED, action=None, attempts=(skipped,))
        self._steps_used += 1
        first = self.call(self._primary, obs)
        if first.status not in FAILURES:
            return self._finish(index, first, (first,), None)
        ctx = _Context(self, obs)
        res = self.recovery.recover(first, ctx)
        if res.switch_to is not None:
            self._primary = res.switch_to
        attempts = (first, *res.attempts)
        if res.outcome is None:
            return StepResult(
                step=index,
                status=first.status,
                action=self.safe_action(),
                attempts=attempts,
                recovery=res.strategy,
                aborted=True,
            )
        return self._finish(index, res.outcome, attempts, res.strategy)

    def _finish(self, index: int, final: Outcome, attempts: tuple[Outcome, ...], recovery: str | None) -> StepResult:
        if final.action is not None:
            for gi in self._gripper:
                self._gripper[gi] = final.action[gi]
        return StepResult(step=index, status=final.status, action=final.action, attempts=attempts, recovery=recovery)


class _Context:
    """What recovery strategies see of the invoker during one step."""

    __slots__ = ("_invoker", "_obs")

    def __init__(self, invoker: EcmInvoker, obs: Mapping[str, Any]) -> None:
        self._invoker = invoker
        self._obs = obs

    @property
    def primary(self) -> LoadedEcm:
        return self._invoker.primary

    def call(self, ecm: LoadedEcm) -> Outcome:
        return self._invoker.call(ecm, self._obs)
