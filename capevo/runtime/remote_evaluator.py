"""The client side of runtime workers: :class:`RemoteEvaluator` runs episodes on them, and
:func:`list_workers` lists them (keys and payloads: :mod:`capevo.runtime.worker_protocol`; the
server: :mod:`capevo.runtime.worker`).

Invariants:
1. :meth:`RemoteEvaluator.evaluate` returns one outcome per seed, in seed order, each from
   exactly one episode, whichever workers ran them and however many died on the way (see
   :mod:`capevo.runtime.fanout` for the split and the retry rules).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import queue
import threading
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from capevo.errors import (
    CapevoError,
    Invalid,
    Timeout,
    Unavailable,
    error_from_payload,
)
from capevo.records import Origin
from capevo.registry.keys import DEFAULT_NAMESPACE
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.evaluator import check_seeds, check_versions
from capevo.runtime.fanout import DEFAULT_MAX_ATTEMPTS, Part, SeedLedger
from capevo.runtime.tasks import task_spec
from capevo.runtime.worker_protocol import (
    DEFAULT_EVALUATE_TIMEOUT_S,
    DISCOVERY_TIMEOUT_S,
    Adoption,
    EvaluateRequest,
    RuntimeKeys,
    check_overrides,
    decode_outcomes,
    first_line,
    validate_worker_id,
    zenoh_client_config,
)

log = logging.getLogger(__name__)


class _SessionOwner:
    """A Zenoh session given by the caller, or opened (and later closed) here."""

    def __init__(
        self,
        *,
        session: zenoh.Session | None,
        connect: Sequence[str] | str | None,
        user: str | None,
        password: str | None,
    ) -> None:
        from capevo.registry.zconfig import split_endpoints

        if (session is None) == (not split_endpoints(connect)):
            raise Invalid("give exactly one of session or connect", details={"field": "connect"})
        self._own = session is None
        if session is None:
            endpoints = split_endpoints(connect)
            try:
                session = zenoh.open(zenoh_client_config(endpoints, user, password))
            except zenoh.ZError as exc:
                raise Unavailable(
                    f"cannot reach {', '.join(endpoints)}: {first_line(exc)}", details={"connect": list(endpoints)}
                ) from None
        self.session: zenoh.Session = session
        self._closed = False

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._own:
            with contextlib.suppress(zenoh.ZError):
                self.session.close()


class RemoteEvaluator:
    """:class:`capevo.runtime.evaluation.Evaluator` served by runtime workers over Zenoh.

    One call's seeds are split across every live worker of the task (found by their
    ``<ns>/runtime/*/serves/<task>`` liveliness tokens) and run concurrently, one query per
    worker; the outcomes are merged back in seed order (:mod:`capevo.runtime.fanout`). A worker
    that dies mid-call (its liveliness token goes, or its query ends without outcomes) or
    refuses with ``unavailable`` (shutting down, queue full) has its unfinished seeds re-split
    across the workers still alive, re-listing them first if none is left; every seed is
    counted once (invariant 7). Any other error from a worker (``invalid``, ``not_found``, an
    evaluation failure) ends the call with that error, as a local evaluation would.

    It also implements :class:`capevo.learner.base.CandidateEvaluator`: ``overrides`` travel
    inline in the request, so a learner's unpublished candidates run on the workers too.

    Args:
        connect: Endpoint(s) of the registry router (or any router the workers reach); or
        session: an open Zenoh session to use (not closed here).
        namespace: The registry's namespace.
        user, password: Zenoh credentials when ``connect`` is given.
        worker_id: Ask only this worker (no split); default every live worker of the task.
        timeout: Seconds to wait for all the outcomes of one call.
        max_attempts: Dispatches of one seed before the call gives up with ``unavailable``.
        trace_dir: When given, each worker sends its part's trace file back with the outcomes
            and it is written here (``<worker_id>-<file name>``); the outcomes' ``trace_path``
            names these local copies, so learners read a remote worker's episodes without a
            shared disk. None leaves each ``trace_path`` as the worker's own (None when the
            worker keeps no traces).

    Raises:
        Invalid: neither or both of ``connect``/``session``; bad namespace, worker id, timeout or
            max_attempts.
        Unavailable: the session cannot open.
    """

    def __init__(
        self,
        connect: Sequence[str] | str | None = None,
        *,
        session: zenoh.Session | None = None,
        namespace: str = DEFAULT_NAMESPACE,
        user: str | None = None,
        password: str | None = None,
        worker_id: str | None = None,
        timeout: float = DEFAULT_EVALUATE_TIMEOUT_S,
        max_attempts: int = DEFAULT_MAX_ATTEMPTS,
        trace_dir: str | os.PathLike[str] | None = None,
    ) -> None:
        self.keys = RuntimeKeys(namespace)
        self.trace_dir = Path(trace_dir) if trace_dir is not None else None
        self.worker_id = validate_worker_id(worker_id) if worker_id is not None else None
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
            raise Invalid(
                f"timeout must be a positive number of seconds, got {timeout!r}", details={"field": "timeout"}
            )
        self.timeout = float(timeout)
        SeedLedger((), max_attempts=max_attempts)  # checks max_attempts
        self.max_attempts = max_attempts
        self.last_call: dict[str, Any] = {}
        """How the last call went: ``parts``, ``failed_parts``, ``dropped``, ``workers``."""
        self._owner = _SessionOwner(session=session, connect=connect, user=user, password=password)
        self._listeners: set[queue.Queue[tuple[str, Any, Any]]] = set()
        self._listeners_lock = threading.Lock()
        try:
            # One subscriber for the evaluator's life: a call learns of a death while it waits.
            self._liveliness: Any = self._owner.session.liveliness().declare_subscriber(
                self.keys.alive_all(), zenoh.handlers.Callback(self._on_liveliness)
            )
        except zenoh.ZError as exc:
            self._owner.close()
            raise Unavailable(f"cannot watch the runtime workers: {first_line(exc)}") from None

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        worker = self.keys.worker_of(str(sample.key_expr))
        if worker is None:
            return
        with self._listeners_lock:
            for q in self._listeners:
                q.put(("gone", worker, None))

    def live_workers(self, task: str, timeout: float = DISCOVERY_TIMEOUT_S) -> list[str]:
        """The ids of the workers whose ``serves/<task>`` token is alive, sorted.

        Raises:
            Invalid: unknown task. Unavailable: the liveliness query failed.
        """
        if self.worker_id is not None:
            return [self.worker_id]
        key = self.keys.serves_task(task)
        found = set()
        try:
            for reply in self._owner.session.liveliness().get(key, timeout=max(timeout, 0.1)):
                if reply.ok is not None:
                    worker = self.keys.worker_of(str(reply.ok.key_expr))
                    if worker is not None:
                        found.add(worker)
        except zenoh.ZError as exc:
            raise Unavailable(f"{key}: listing runtime workers failed: {first_line(exc)}") from None
        return sorted(found)

    def evaluate(
        self,
        task: str,
        versions: Mapping[str, int],
        seeds: Sequence[int],
        *,
        overrides: Mapping[str, bytes] | None = None,
        override_origin: Origin | None = None,
    ) -> list[EpisodeOutcome]:
        """Run the episodes on the task's live workers; one outcome per seed, in seed order.

        Args:
            task, versions, seeds: As :meth:`capevo.runtime.evaluation.Evaluator.evaluate`.
            overrides: ECM name to artifact bytes run in place of that ECM's artifact (sent
                inline; see the module docstring).
            override_origin: The origin the overrides run under (default the overridden
                version's); inline code must run in the sandbox.

        Raises:
            Invalid: bad arguments (checked here first) or refused by a worker.
            Forbidden: an override the worker would run in its own process.
            Unavailable: no worker serves the task, or every worker that could run some seed
                died or refused.
            Timeout: not every outcome within ``timeout``.
            CapevoError: whatever a worker's evaluation raised (same class and code).
        """
        spec = task_spec(task)
        if override_origin is not None and not isinstance(override_origin, Origin):
            raise Invalid(f"override_origin must be an Origin, got {override_origin!r}", details={"field": "origin"})
        request = EvaluateRequest(
            task=spec.name,
            versions=check_versions(versions),
            seeds=tuple(check_seeds(seeds)),
            overrides=check_overrides(overrides, spec.name),
            override_origin=override_origin,
            traces=self.trace_dir is not None,
        )
        deadline = time.monotonic() + self.timeout
        ledger = SeedLedger(request.seeds, max_attempts=self.max_attempts)
        events: queue.Queue[tuple[str, Any, Any]] = queue.Queue()
        tokens: dict[int, zenoh.CancellationToken] = {}
        out: set[str] = set()  # workers this call no longer sends to: dead or refusing
        used: set[str] = set()
        refusals: list[Unavailable] = []
        with self._listeners_lock:
            self._listeners.add(events)
        try:
            live = set(self.live_workers(spec.name, min(DISCOVERY_TIMEOUT_S, self.timeout)))
            while not ledger.done:
                if ledger.pool:
                    candidates = live - out
                    if not candidates:  # every worker we knew is gone: one may have joined since
                        live |= set(self.live_workers(spec.name, min(DISCOVERY_TIMEOUT_S, _left(deadline))))
                        candidates = live - out
                    if not candidates:
                        raise self._no_worker(spec.name, ledger, tried=sorted(used), refusals=refusals)
                    for part in ledger.dispatch(candidates):
                        used.add(part.worker_id)
                        tokens[part.part_id] = self._send(part, request, events, deadline)
                try:
                    kind, subject, body = events.get(timeout=_left(deadline))
                except queue.Empty:
                    raise Timeout(
                        f"{self.keys.serves_task(spec.name)}: not every outcome within {self.timeout:g}s",
                        details={"key": self.keys.serves_task(spec.name), "pending": len(ledger.in_flight())},
                    ) from None
                if kind == "gone":
                    out.add(subject)
                    for part in ledger.in_flight(subject):
                        self._lose(ledger, part, tokens, "its liveliness token went away")
                    continue
                part = next((p for p in ledger.in_flight() if p.part_id == subject), None)
                if kind == "ok":
                    payload, attachment = body
                    worker, outcomes = decode_outcomes(payload)
                    local = self._keep_trace(worker, outcomes, attachment)
                    if local is not None:
                        outcomes = [dataclasses.replace(o, trace_path=str(local)) for o in outcomes]
                    if ledger.complete(subject, outcomes) == 0 and local is not None:
                        local.unlink(missing_ok=True)  # every episode in it was counted from another part
                elif kind == "err":
                    if part is None:  # a part given up already; its late error changes nothing
                        continue
                    err = _reply_error(body, self.keys.evaluate(part.worker_id), self.timeout)
                    if not isinstance(err, Unavailable):
                        raise err
                    out.add(part.worker_id)
                    refusals.append(err)
                    self._lose(ledger, part, tokens, err.message)
                elif kind == "end" and part is not None:
                    # The query ended without a reply: its worker vanished with it.
                    out.add(part.worker_id)
                    self._lose(ledger, part, tokens, "its query ended without outcomes")
            return ledger.merged()
        finally:
            with self._listeners_lock:
                self._listeners.discard(events)
            for token in tokens.values():
                token.cancel()
            self.last_call = {
                "parts": len(tokens),
                "failed_parts": ledger.failed_parts,
                "dropped": ledger.dropped,
                "workers": sorted(used),
            }

    def _send(
        self, part: Part, request: EvaluateRequest, events: queue.Queue[tuple[str, Any, Any]], deadline: float
    ) -> zenoh.CancellationToken:
        """Query ``part``'s worker; its reply and its end land on ``events`` as ``(kind, part_id, body)``."""
        key = self.keys.evaluate(part.worker_id)
        payload = dataclasses.replace(request, seeds=part.seeds).to_json()
        token = zenoh.CancellationToken()
        pid = part.part_id

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                extra = reply.ok.attachment
                trace = extra.to_bytes() if extra is not None else None
                events.put(("ok", pid, (reply.ok.payload.to_bytes(), trace)))
            else:
                events.put(("err", pid, reply.err.payload.to_bytes() if reply.err is not None else b""))

        def on_end() -> None:
            events.put(("end", pid, None))

        try:
            self._owner.session.get(
                key,
                zenoh.handlers.Callback(on_reply, on_end),
                payload=payload,
                # a little past the call's deadline: the call's own Timeout is the one raised
                timeout=_left(deadline) + 1.0,
                target=zenoh.QueryTarget.BEST_MATCHING,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.BLOCK,
                cancellation_token=token,
            )
        except zenoh.ZError as exc:
            raise Unavailable(f"{key}: query failed: {first_line(exc)}", details={"key": key}) from None
        log.debug("sent seeds %s to %s (part %d)", list(part.seeds), part.worker_id, pid)
        return token

    def _keep_trace(self, worker: str, outcomes: Sequence[EpisodeOutcome], trace: bytes | None) -> Path | None:
        """Write a part's trace file under :attr:`trace_dir`; its path, or None when there is none."""
        if self.trace_dir is None or not trace:
            return None
        remote = next((o.trace_path for o in outcomes if o.trace_path), None)
        name = Path(remote).name if remote else f"eval-{uuid.uuid4().hex[:12]}.mcap"
        path = self.trace_dir / f"{worker}-{name}"
        self.trace_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
        tmp.write_bytes(trace)
        os.replace(tmp, path)  # a reader never sees half a file
        return path

    @staticmethod
    def _lose(ledger: SeedLedger, part: Part, tokens: Mapping[int, zenoh.CancellationToken], why: str) -> None:
        back = ledger.fail(part.part_id)
        token = tokens.get(part.part_id)
        if token is not None:
            token.cancel()
        if back:
            log.warning(
                "runtime worker %s lost seeds %s (%s); re-running them elsewhere",
                part.worker_id,
                [ledger.seeds[i] for i in back],
                why,
            )

    def _no_worker(
        self, task: str, ledger: SeedLedger, *, tried: list[str], refusals: Sequence[Unavailable]
    ) -> Unavailable:
        if refusals and len(tried) == 1:
            return refusals[-1]  # the one worker asked said why (busy, shutting down)
        if self.worker_id is not None:
            key = self.keys.evaluate(self.worker_id)
            return Unavailable(
                f"{key}: runtime worker {self.worker_id!r} did not answer (namespace {self.keys.namespace!r}); "
                "is it running?",
                details={"key": key},
            )
        key = self.keys.serves_task(task)
        if not tried:
            return Unavailable(
                f"{key}: no runtime worker of task {task!r} answered (namespace {self.keys.namespace!r}); "
                "is one running?",
                details={"key": key},
            )
        lost = [ledger.seeds[i] for i in ledger.pool]
        return Unavailable(
            f"{key}: runtime workers {', '.join(tried)} of task {task!r} died or refused with seeds {lost} "
            "unfinished, and no other worker is alive",
            details={"key": key, "seeds": lost},
        )

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._liveliness.undeclare()
        self._owner.close()

    def __enter__(self) -> RemoteEvaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _left(deadline: float) -> float:
    return max(deadline - time.monotonic(), 0.0)


def _reply_error(body: bytes, key: str, timeout: float) -> CapevoError:
    """The error an error reply carries (Zenoh's own query timeout says ``Timeout``)."""
    if body == b"Timeout":
        return Timeout(f"{key}: no outcomes within {timeout:g}s", details={"key": key})
    return error_from_payload(body)


def list_workers(
    connect: Sequence[str] | str | None = None,
    *,
    session: zenoh.Session | None = None,
    namespace: str = DEFAULT_NAMESPACE,
    user: str | None = None,
    password: str | None = None,
    timeout: float = 3.0,
) -> list[Adoption]:
    """Every runtime worker that answers ``<ns>/runtime/*/adopted``, sorted by worker id.

    Raises:
        Invalid: neither or both of ``connect``/``session``. Unavailable: the session cannot open.
    """
    keys = RuntimeKeys(namespace)
    owner = _SessionOwner(session=session, connect=connect, user=user, password=password)
    try:
        found: dict[str, Adoption] = {}
        try:
            replies = owner.session.get(
                keys.adopted_all(),
                timeout=timeout,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    adoption = Adoption.from_dict(json.loads(reply.ok.payload.to_bytes()))
                except (Invalid, ValueError) as exc:
                    log.warning("ignoring a malformed adoption reply on %s: %s", reply.ok.key_expr, exc)
                    continue
                found[adoption.worker_id] = adoption
        except zenoh.ZError as exc:
            raise Unavailable(f"listing runtime workers failed: {first_line(exc)}") from None
        return [found[k] for k in sorted(found)]
    finally:
        owner.close()
