"""Host side of the sandbox: one long-lived worker process per untrusted code skill.

:class:`SandboxedSkill` validates the source in the host, starts a worker
(:mod:`capevo.runtime.sandbox.worker`) as a fresh ``python -I`` subprocess — never a fork,
so an open Zenoh session or torch thread pool is never duplicated — and then exchanges one
request/reply frame per step over pipes.

Timeouts: each step waits at most ``timeout_s`` of wall-clock time for the reply. On
overrun the worker is SIGKILLed, a replacement is started at once in the background (its
handshake is awaited at the next call, outside that call's timeout), and the call raises
:class:`capevo.errors.Timeout`. A worker that dies (CPU limit, crash, protocol garbage) is
replaced the same way and the call raises :class:`WorkerDied`. After ``max_restarts``
replacements the skill is dead: every later call raises :class:`WorkerDied` at once.

Invariants:
1. A hanging, crashing or lying worker never blocks the host longer than the call's
   timeout (plus process-kill latency) and never raises anything but :class:`Timeout`,
   :class:`WorkerDied`, :class:`SkillRaised` or :class:`BadOutput` from :meth:`step`.
2. The host never unpickles worker output; replies are size-capped JSON.
3. At most one worker process per :class:`SandboxedSkill` is alive, and :meth:`close`
   (or garbage collection) kills it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from capevo.errors import CapevoError, Invalid, Timeout, error_class
from capevo.runtime.sandbox.limits import WorkerLimits
from capevo.runtime.sandbox.namespace import MAX_ACTION_ELEMENTS, BadOutput, check_params, merge_params
from capevo.runtime.sandbox.protocol import (
    MAX_REPLY_BYTES,
    FrameReader,
    PeerClosed,
    ProtocolError,
    encode_arrays,
    encode_frame,
)
from capevo.runtime.sandbox.validator import ALLOWED_IMPORTS, validate_source
from capevo.runtime.sandbox.worker import BOOTSTRAP

_CAPEVO_ROOT = str(Path(__file__).resolve().parents[3])
_WORKER_ENV = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "PATH": "/usr/bin:/bin",
    "LC_ALL": "C.UTF-8",
}


class WorkerDied(Exception):
    """The worker process ended or broke the protocol during a call."""


class SkillRaised(Exception):
    """The skill raised inside the worker; the message is the worker's description."""


@dataclass(frozen=True, slots=True)
class SkillStep:
    """One step of a skill: ``done`` from its termination check, else the raw action."""

    done: bool
    action: np.ndarray | None


@dataclass(frozen=True, slots=True, kw_only=True)
class SandboxConfig:
    """How sandbox workers are started and limited.

    Args:
        limits: Kernel limits the worker applies to itself.
        startup_timeout_s: Wall-clock limit for start, imports, lock-down and the skill's
            top-level code.
        max_restarts: Replacements after timeouts or deaths before the skill is declared dead.
        max_reply_bytes: Largest reply frame accepted from a worker.
        allowed_imports: Modules skills may import.
        python: Interpreter for workers; ``None`` means ``sys.executable``.
    """

    limits: WorkerLimits = field(default_factory=WorkerLimits)
    startup_timeout_s: float = 30.0
    max_restarts: int = 3
    max_reply_bytes: int = MAX_REPLY_BYTES
    allowed_imports: tuple[str, ...] = tuple(sorted(ALLOWED_IMPORTS))
    python: str | None = None


class _Proc:
    """A running worker and its reader; mutable holder so the finalizer sees replacements."""

    __slots__ = ("popen", "reader", "ready")

    def __init__(self, popen: subprocess.Popen[bytes], reader: FrameReader) -> None:
        self.popen = popen
        self.reader = reader
        self.ready = False


def _kill(holder: list[_Proc | None]) -> None:
    proc = holder[0]
    holder[0] = None
    if proc is None:
        return
    p = proc.popen
    if p.poll() is None:
        p.kill()
    with contextlib.suppress(subprocess.TimeoutExpired):  # a SIGKILLed process always exits
        p.wait(timeout=5)
    for stream in (p.stdin, p.stdout):
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()


class SandboxedSkill:
    """A code skill running in its own locked-down worker process.

    Args:
        source: Skill source (see :mod:`capevo.runtime.ecm.code` for the contract).
        params_override: Values replacing some of the source's ``PARAMS``.
        config: Limits and process settings.
        filename: Name shown in errors.
        _unsafe_skip_validation: TEST HOOK ONLY. Skips the AST validation in host and
            worker so tests can prove the kernel layers hold on their own.

    Raises:
        SandboxViolation: the source breaks a validation rule.
        Invalid: syntax error, contract not met, top-level code raised, or bad params.
        WorkerDied: the worker could not be started.
    """

    in_process = False

    def __init__(
        self,
        source: str,
        params_override: Mapping[str, Any] | None = None,
        *,
        config: SandboxConfig | None = None,
        filename: str = "<skill>",
        _unsafe_skip_validation: bool = False,
    ) -> None:
        self._config = config or SandboxConfig()
        self._validate = not _unsafe_skip_validation
        if self._validate:
            validate_source(source, filename=filename, allowed_imports=self._config.allowed_imports)
        self._source = source
        self._filename = filename
        self._override: dict[str, float] = check_params(params_override or {}, where="params_override")
        self._holder: list[_Proc | None] = [None]
        self._finalizer = weakref.finalize(self, _kill, self._holder)
        self.restarts = 0
        self.dead_reason: str | None = None
        self.layers: dict[str, Any] = {}
        self.params: dict[str, float] = {}
        self.defaults: dict[str, float] = {}
        try:
            self._spawn()
            self._handshake()
        except PeerClosed as exc:
            _kill(self._holder)
            raise WorkerDied(f"worker failed to start: {exc}") from None
        except BaseException:
            _kill(self._holder)
            raise

    # --- process management ----------------------------------------------------------

    @property
    def pid(self) -> int | None:
        """Process id of the current worker, if one is running."""
        proc = self._holder[0]
        return proc.popen.pid if proc is not None else None

    def _spawn(self) -> None:
        popen = subprocess.Popen(
            [self._config.python or sys.executable, "-I", "-B", "-c", BOOTSTRAP, _CAPEVO_ROOT],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=dict(_WORKER_ENV),
            cwd="/",
            close_fds=True,
            start_new_session=True,  # terminal signals go to the host only
            bufsize=0,
        )
        if popen.stdout is None or popen.stdin is None:  # pragma: no cover - PIPE guarantees both
            popen.kill()
            raise WorkerDied("worker pipes missing")
        os.set_blocking(popen.stdout.fileno(), False)
        self._holder[0] = _Proc(popen, FrameReader(popen.stdout.fileno(), max_frame=self._config.max_reply_bytes))
        init = {
            "op": "init",
            "source": self._source,
            "filename": self._filename,
            "params": self._override,
            "validate": self._validate,
            "allowed_imports": list(self._config.allowed_imports),
            "limits": self._config.limits.to_dict(),
        }
        # The worker reads this first thing; a frame under the pipe buffer (64 KiB, so
        # nearly every skill) sits there while the worker starts and we return at once.
        self._write(encode_frame(init))

    def _handshake(self) -> None:
        proc = self._holder[0]
        if proc is None:
            raise WorkerDied("no worker process")
        deadline = time.monotonic() + self._config.startup_timeout_s
        try:
            reply = proc.reader.read(deadline)
        except TimeoutError:
            _kill(self._holder)
            raise WorkerDied(f"worker did not start within {self._config.startup_timeout_s}s") from None
        except (PeerClosed, ProtocolError) as exc:
            reason = self._death_reason(exc)
            _kill(self._holder)
            raise WorkerDied(f"worker failed to start: {reason}") from None
        if not reply.get("ok"):
            _kill(self._holder)
            cls = error_class(str(reply.get("kind", "internal")))
            details = reply.get("details") if isinstance(reply.get("details"), dict) else None
            raise cls(str(reply.get("error", "worker refused the skill")), details=details)
        self.layers = dict(reply.get("layers") or {})
        self.params = check_params(reply.get("params") or {}, where="worker params")
        self.defaults = check_params(reply.get("defaults") or {}, where="worker defaults")
        proc.ready = True

    def _write(self, data: bytes) -> None:
        proc = self._holder[0]
        if proc is None or proc.popen.stdin is None:
            raise WorkerDied("no worker process")
        try:
            proc.popen.stdin.write(data)
        except (BrokenPipeError, ValueError, OSError) as exc:
            raise PeerClosed(str(exc)) from None

    def _death_reason(self, exc: BaseException) -> str:
        proc = self._holder[0]
        if proc is None or isinstance(exc, ProtocolError):
            return f"protocol error: {exc}"  # it is alive and lying; it gets killed anyway
        try:
            code = proc.popen.wait(timeout=0.5)  # EOF came first; the exit status follows
        except subprocess.TimeoutExpired:
            return f"{type(exc).__name__}: {exc} (worker still running)"
        if code == -signal.SIGXCPU:
            limit = self._config.limits.cpu_seconds_per_call
            return f"worker killed by SIGXCPU: CPU limit of {limit}s per call exceeded"
        if code < 0:
            try:
                return f"worker killed by {signal.Signals(-code).name}"
            except ValueError:
                return f"worker killed by signal {-code}"
        return f"worker exited with status {code}"

    def _replace(self, reason: str) -> None:
        """Kill the current worker and start a successor, or declare the skill dead."""
        _kill(self._holder)
        if self.restarts >= self._config.max_restarts:
            self.dead_reason = f"{reason} (after {self.restarts} restart(s))"
            return
        self.restarts += 1
        try:
            self._spawn()
        except (OSError, PeerClosed, WorkerDied) as exc:
            self.dead_reason = f"{reason}; could not restart worker: {exc}"
            _kill(self._holder)

    def _ensure_ready(self) -> _Proc:
        proc = self._holder[0]
        if proc is None:
            raise WorkerDied(f"{self._filename}: skill is dead: {self.dead_reason or 'closed'}")
        if not proc.ready:
            try:
                self._handshake()
            except (WorkerDied, CapevoError) as exc:
                self.dead_reason = f"restart failed: {exc}"
                _kill(self._holder)
                raise WorkerDied(f"{self._filename}: {self.dead_reason}") from None
        return proc

    # --- calls -----------------------------------------------------------------------

    def step(self, inputs: Mapping[str, np.ndarray], *, timeout_s: float) -> SkillStep:
        """Run the skill's ``done`` then ``act`` on one observation in the worker.

        Args:
            inputs: Marshalled observation arrays.
            timeout_s: Wall-clock limit for this call's round trip.

        Returns:
            The step: ``done`` True with no action, or the raw action array.

        Raises:
            Timeout: no reply in time; the worker was killed and is being replaced.
            WorkerDied: the worker died or sent garbage; replaced unless the skill is dead.
            SkillRaised: the skill raised; the worker lives on.
            BadOutput: the skill returned something that is not a numeric action.
        """
        proc = self._ensure_ready()
        try:
            self._write(encode_frame({"op": "step", "obs": encode_arrays(inputs)}))
            reply = proc.reader.read(time.monotonic() + timeout_s)
        except TimeoutError:
            self._replace(f"timed out after {timeout_s}s")
            raise Timeout(f"{self._filename}: no reply within {timeout_s}s; worker killed") from None
        except (PeerClosed, ProtocolError) as exc:
            reason = self._death_reason(exc)
            self._replace(reason)
            raise WorkerDied(f"{self._filename}: {reason}") from None
        return self._parse_step(reply)

    def _parse_step(self, reply: Mapping[str, Any]) -> SkillStep:
        if not reply.get("ok"):
            kind = reply.get("kind")
            text = str(reply.get("error", ""))
            if kind == "bad_output":
                raise BadOutput(text)
            if kind == "exception":
                raise SkillRaised(text)
            self._replace(f"worker reported {kind}: {text}")
            raise WorkerDied(f"{self._filename}: worker reported {kind}: {text}")
        if reply.get("done") is True:
            return SkillStep(done=True, action=None)
        wire = reply.get("action")
        try:
            shape, data = wire  # type: ignore[misc]
            shape_t = tuple(int(s) for s in shape)
            if any(s < 0 for s in shape_t) or len(data) > MAX_ACTION_ELEMENTS:
                raise ValueError("bad size")
            arr = np.array(data, dtype=np.float64).reshape(shape_t)
        except (TypeError, ValueError, OverflowError):
            raise BadOutput(f"{self._filename}: malformed action in worker reply") from None
        return SkillStep(done=False, action=arr)

    def set_params(self, params: Mapping[str, Any]) -> dict[str, float]:
        """Replace θ (some of ``PARAMS``) without restarting; later restarts keep it.

        Returns:
            The merged parameters now in force.

        Raises:
            Invalid: unknown key or non-finite value.
            WorkerDied: the worker did not acknowledge.
        """
        merged = merge_params(self.defaults, params)
        proc = self._ensure_ready()
        try:
            self._write(encode_frame({"op": "params", "params": merged}))
            reply = proc.reader.read(time.monotonic() + self._config.startup_timeout_s)
        except (TimeoutError, PeerClosed, ProtocolError) as exc:
            self._replace(f"params update failed: {exc}")
            raise WorkerDied(f"{self._filename}: params update failed: {exc}") from None
        if not reply.get("ok"):
            raise Invalid(str(reply.get("error", "worker refused params")))
        self._override = merged
        self.params = check_params(reply.get("params") or {}, where="worker params")
        return dict(self.params)

    def ping(self, *, timeout_s: float = 5.0) -> float:
        """Round trip of an empty request in seconds (for benchmarks and health checks)."""
        proc = self._ensure_ready()
        t0 = time.perf_counter()
        self._write(encode_frame({"op": "ping"}))
        proc.reader.read(time.monotonic() + timeout_s)
        return time.perf_counter() - t0

    def close(self) -> None:
        """Ask the worker to exit, then make sure it is gone. Idempotent."""
        proc = self._holder[0]
        if proc is not None and proc.popen.poll() is None:
            try:
                self._write(encode_frame({"op": "exit"}))
                proc.popen.wait(timeout=1.0)
            except (PeerClosed, WorkerDied, subprocess.TimeoutExpired):
                pass
        _kill(self._holder)
        self.dead_reason = self.dead_reason or "closed"

    def __enter__(self) -> SandboxedSkill:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
