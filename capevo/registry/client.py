"""The Zenoh registry client: the :class:`~capevo.registry.api.Registry` API over the network.

A :class:`Client` opens a Zenoh session in client mode (multicast scouting off) to the
registry router, sends one query per call, and turns every outcome into a record or a
:class:`capevo.errors.CapevoError`:

* an error reply -> the same error subclass the registry raised (``error_from_payload``);
* no reply before the timeout -> :class:`Timeout`;
* no reply at all, at once -> the router refused or nobody serves the key: when the
  registry's liveliness token is visible it is :class:`Forbidden` (Zenoh access control
  drops refused queries silently), otherwise :class:`Unavailable`;
* a session that cannot open (router down, wrong user or password) -> :class:`Unavailable`.

Invariants:
1. Every public method raises only :class:`CapevoError` subclasses; none blocks longer
   than its timeout.
2. Arguments are checked before anything is sent, by the same checks the server and
   :class:`LocalRegistry` run, so a bad call fails with the same error wherever it runs.
3. ``get_artifact`` returns only bytes whose sha256 matches what the registry says.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import secrets
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

import zenoh

from capevo.errors import (
    CapevoError,
    Corrupt,
    Forbidden,
    Invalid,
    Timeout,
    TooLarge,
    Unavailable,
    error_from_payload,
)
from capevo.records import (
    AuditEvent,
    CapabilitySet,
    EcmDetail,
    EcmSummary,
    EcmVersion,
    PublishSpec,
    VerifyReport,
)
from capevo.records.names import validate_name, validate_version
from capevo.registry.keys import DEFAULT_NAMESPACE, Keys
from capevo.registry.local import default_actor, validate_spec
from capevo.registry.uploads import PART_BYTES
from capevo.registry.wire import (
    ArtifactMeta,
    UploadPart,
    decode_event,
    decode_reply,
    encode_command,
    list_of,
    validate_actor,
)
from capevo.registry.zconfig import client_config, split_endpoints

log = logging.getLogger(__name__)

T = TypeVar("T")
EventCallback = Callable[[AuditEvent, EcmVersion], Any]
# Seconds added to a publish's timeout per byte of artifact: a slow link must not time out a 64 MB push.
SECONDS_PER_BYTE = 1.0 / (4 * 2**20)
_ZENOH_TIMEOUT_REPLY = b"Timeout"
# Version replies this client keeps decoded. Resolves repeat: most replies are bytes it has
# decoded before, and decoding is most of a resolve's client-side CPU (issue 21).
DECODED_VERSIONS_KEPT = 256  # also the most active-version keys kept


def _received(value: Any) -> int:
    """The byte count in a part's acknowledgement ``{"upload", "received"}``."""
    received = value["received"]
    if isinstance(received, bool) or not isinstance(received, int):
        raise TypeError(f"received must be an integer, got {received!r:.40}")
    return received


class EventSubscription:
    """A live subscription to registry events; :meth:`close` ends it."""

    def __init__(self, subscriber: zenoh.Subscriber[Any], on_close: Callable[[EventSubscription], None]) -> None:
        self._subscriber = subscriber
        self._on_close = on_close
        self._closed = False

    def close(self) -> None:
        """Stop receiving events. Idempotent."""
        if self._closed:
            return
        self._closed = True
        # A closed session has already undeclared it.
        with contextlib.suppress(zenoh.ZError):
            self._subscriber.undeclare()
        self._on_close(self)

    def __enter__(self) -> EventSubscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Client:
    """The registry API over Zenoh.

    Args:
        connect: Endpoint(s) of the registry router (or any router that reaches it).
        namespace: Key prefix the registry serves.
        user, password: Zenoh usrpwd credentials; both or neither.
        timeout: Seconds to wait for a reply (publishes get extra time per MB).
        actor: Sent with this client's mutations unless a call passes ``actor=``; defaults
            to ``user`` or the OS user. A secured registry records ``user`` as the actor
            whatever this says (an operator's differing actor is kept as ``on_behalf_of``);
            an open one records it as claimed.
        artifact_timeout: Seconds to wait for an artifact download.

    Raises:
        Invalid: bad namespace, endpoint, credentials or actor.
        Unavailable: the session cannot open (nothing listening, or wrong user/password:
            Zenoh refuses to open a session with bad credentials).
    """

    def __init__(
        self,
        connect: Sequence[str] | str,
        *,
        namespace: str = DEFAULT_NAMESPACE,
        user: str | None = None,
        password: str | None = None,
        timeout: float = 10.0,
        actor: str | None = None,
        artifact_timeout: float = 120.0,
    ) -> None:
        self._keys = Keys(namespace)
        self._connect = split_endpoints(connect)
        for name, value in (("timeout", timeout), ("artifact_timeout", artifact_timeout)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise Invalid(f"{name} must be a positive number of seconds, got {value!r}", details={"field": name})
        self._timeout = float(timeout)
        self._artifact_timeout = float(artifact_timeout)
        self._user = user
        self._actor = validate_actor(actor if actor is not None else (user or default_actor()))
        config = client_config(connect=self._connect, user=user, password=password)
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as exc:
            hint = (
                "the user/password was refused, or nothing listens there"
                if user is not None
                else "nothing listens there, or the registry is secured and needs a user and password"
            )
            raise Unavailable(
                f"cannot reach the registry at {', '.join(self._connect)} ({hint}): {_first_line(exc)}",
                details={"connect": list(self._connect)},
            ) from None
        self._lock = threading.Lock()
        self._subscriptions: list[EventSubscription] = []
        self._info: dict[str, Any] | None = None
        self._decoded: dict[bytes, EcmVersion] = {}
        self._active_keys: dict[str, str] = {}
        self._closed = False

    # --- plumbing ---------------------------------------------------------------------
    @property
    def namespace(self) -> str:
        return self._keys.namespace

    @property
    def actor(self) -> str | None:
        return self._actor

    def _who(self, actor: str | None) -> str | None:
        return self._actor if actor is None else validate_actor(actor)

    def _query(
        self,
        key: str,
        *,
        parameters: Mapping[str, str] | None = None,
        payload: bytes | None = None,
        attachment: bytes | None = None,
        timeout: float | None = None,
    ) -> zenoh.Sample:
        """Send one query and return its one successful sample, or raise what went wrong."""
        if self._closed:
            raise Unavailable("this registry client is closed")
        timeout = self._timeout if timeout is None else timeout
        selector: Any = zenoh.Selector(key, dict(parameters)) if parameters else key
        started = time.monotonic()
        try:
            replies = self._session.get(
                selector,
                payload=payload,
                attachment=attachment,
                timeout=timeout,
                # Large requests and replies are fragmented; blocking keeps fragments from being dropped.
                congestion_control=zenoh.CongestionControl.BLOCK,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            for reply in replies:
                sample = reply.ok
                if sample is not None:
                    return sample
                err = reply.err
                body = b"" if err is None else err.payload.to_bytes()
                if body == _ZENOH_TIMEOUT_REPLY:
                    raise Timeout(f"{key}: no reply from the registry within {timeout:g}s", details={"key": key})
                raise error_from_payload(body)
        except zenoh.ZError as exc:
            raise Unavailable(f"{key}: query failed: {_first_line(exc)}", details={"key": key}) from None
        elapsed = time.monotonic() - started
        if elapsed >= timeout * 0.95:
            raise Timeout(f"{key}: no reply from the registry within {timeout:g}s", details={"key": key})
        raise self._no_reply_error(key)

    def _no_reply_error(self, key: str) -> CapevoError:
        # Zenoh's access control drops a refused query without a word, exactly as if nobody
        # served the key; the registry's liveliness token tells the two apart.
        who = f"user {self._user!r}" if self._user else "this client (no user)"
        if self.is_registry_alive():
            return Forbidden(
                f"{key}: the registry is up but did not answer; Zenoh access control probably refused it "
                f"({who} lacks a role allowing this request)",
                details={"key": key, "user": self._user},
            )
        return Unavailable(
            f"{key}: no registry serves namespace {self.namespace!r} via {', '.join(self._connect)}"
            " (or access control hides it from this user)",
            details={"key": key},
        )

    def _read(self, key: str, build: Callable[[Any], T], *, what: str, **params: str) -> T:
        sample = self._query(key, parameters=params or None)
        return decode_reply(sample.payload.to_bytes(), build, what=what)

    def _cmd_key(self, op: str) -> str:
        # A secured registry serves commands only on this user's own key, which its access
        # control grants to this user alone; that is how it knows who asked.
        secured = self._user is not None and self.info().get("secured") is True
        return self._keys.cmd(op, self._user if secured else None)

    def _command(self, op: str, **fields: Any) -> EcmVersion:
        body = encode_command(op, **fields)
        sample = self._query(self._cmd_key(op), payload=body)
        return decode_reply(sample.payload.to_bytes(), EcmVersion.from_dict, what=op)

    # --- registry info and liveliness -------------------------------------------------
    def is_registry_alive(self, timeout: float | None = None) -> bool:
        """Whether a registry's liveliness token ``<ns>/alive/registry`` is visible now."""
        if self._closed:
            return False
        wait = min(self._timeout, 3.0) if timeout is None else timeout
        try:
            replies = self._session.liveliness().get(self._keys.alive(), timeout=wait)
            return any(reply.ok is not None for reply in replies)
        except zenoh.ZError:
            return False

    def info(self) -> dict[str, Any]:
        """The server's limits and settings (``<ns>/info``): protocol, max_artifact_bytes, ..."""
        if self._info is None:
            self._info = self._read(self._keys.info(), _json_object, what="info")
        return dict(self._info)

    # --- reads ------------------------------------------------------------------------
    def list_ecms(self) -> list[EcmSummary]:
        """Every ECM, sorted by name."""
        return self._read(self._keys.ecm_list(), list_of(EcmSummary.from_dict), what="ECM list")

    def get_ecm(self, name: str) -> EcmDetail:
        """One ECM with all its versions. Raises Invalid, NotFound."""
        return self._read(self._keys.ecm(name), EcmDetail.from_dict, what="ECM")

    def get_version(self, name: str, version: int | None = None) -> EcmVersion:
        """Version ``version`` (the active one when None). Raises Invalid, NotFound."""
        # Resolving the active version is the registry's most frequent call: its key is built
        # and checked once per name (issue 21). Only exact str names are kept, so anything
        # else still meets validate_name.
        key = self._active_keys.get(name) if version is None and type(name) is str else None
        if key is None:
            validate_name(name)
            if version is not None:
                validate_version(version)
            key = self._keys.version(name, version)
            if version is None:
                if len(self._active_keys) >= DECODED_VERSIONS_KEPT:
                    self._active_keys.clear()
                self._active_keys[name] = key
        return self._decode_version(self._query(key).payload.to_bytes())

    def _decode_version(self, data: bytes) -> EcmVersion:
        # Records are frozen, so equal reply bytes may share one record; a full memo is
        # dropped whole rather than tracked, since it refills from the next replies.
        record = self._decoded.get(data)
        if record is None:
            record = decode_reply(data, EcmVersion.from_dict, what="version")
            if len(self._decoded) >= DECODED_VERSIONS_KEPT:
                self._decoded.clear()
            self._decoded[data] = record
        return record

    def get_artifact(self, name: str, version: int | None = None) -> bytes:
        """Artifact bytes of a version (the active one when None), checked against their sha256.

        Raises:
            Invalid, NotFound. Corrupt: the bytes do not match the registry's hash.
        """
        validate_name(name)
        if version is not None:
            validate_version(version)
        sample = self._query(self._keys.artifact(name, version), timeout=self._artifact_timeout)
        data = sample.payload.to_bytes()
        if sample.attachment is None:
            raise CapevoError("malformed artifact reply from the registry: no attachment")
        meta = ArtifactMeta.decode(sample.attachment.to_bytes())
        digest = hashlib.sha256(data).hexdigest()
        if digest != meta.sha256 or len(data) != meta.size:
            raise Corrupt(
                f"{meta.name} v{meta.version}: received {len(data)} bytes with sha256 {digest}, "
                f"the registry says {meta.size} bytes with sha256 {meta.sha256}",
                details={"name": meta.name, "version": meta.version},
            )
        return data

    def history(self, name: str | None = None) -> list[AuditEvent]:
        """Audit events of ``name`` (every ECM's when None), in order. Raises Invalid, NotFound."""
        key = self._keys.history_all() if name is None else self._keys.history(name)
        return self._read(key, list_of(AuditEvent.from_dict), what="history")

    def capability_set(self, revision: int | None = None) -> CapabilitySet:
        """C at ``revision`` (default: now). Raises Invalid, NotFound."""
        if revision is None:
            return self._read(self._keys.capability_set(), CapabilitySet.from_dict, what="capability set")
        if isinstance(revision, bool) or not isinstance(revision, int) or revision < 0:
            raise Invalid(f"revision must be a non-negative integer, got {revision!r}", details={"field": "revision"})
        return self._read(
            self._keys.capability_set(), CapabilitySet.from_dict, what="capability set", revision=str(revision)
        )

    def verify(self) -> VerifyReport:
        """Run the registry's integrity check (read-only) and return its report."""
        return self._read(self._keys.verify(), VerifyReport.from_dict, what="verify report")

    # --- mutations --------------------------------------------------------------------
    def publish(self, name: str, artifact: bytes, spec: PublishSpec, *, actor: str | None = None) -> EcmVersion:
        """Upload ``artifact`` as the next candidate version of ``name``.

        Raises:
            Invalid, NotFound (parent), TooLarge (over the server's limit), Forbidden.
        """
        validate_name(name)
        validate_spec(spec)
        if not isinstance(artifact, (bytes, bytearray, memoryview)):
            raise Invalid(f"artifact must be bytes, got {type(artifact).__name__}", details={"field": "artifact"})
        data = bytes(artifact)
        limit = self.info().get("max_artifact_bytes")
        if isinstance(limit, int) and len(data) > limit:
            raise TooLarge(
                f"artifact is {len(data)} bytes; the limit is {limit}", details={"size": len(data), "limit": limit}
            )
        who = self._who(actor)
        if len(data) > PART_BYTES:
            return self._publish_in_parts(name, data, spec, who)
        header = encode_command("publish", name=name, spec=spec, actor=who)
        sample = self._query(
            self._cmd_key("publish"),
            payload=data,
            attachment=header,
            timeout=self._timeout + len(data) * SECONDS_PER_BYTE,
        )
        return decode_reply(sample.payload.to_bytes(), EcmVersion.from_dict, what="publish")

    def _publish_in_parts(self, name: str, data: bytes, spec: PublishSpec, who: str | None) -> EcmVersion:
        """Send ``data`` as ``publish`` parts of at most :data:`PART_BYTES`, in order, each
        acknowledged before the next; the last part's reply is the version. In one payload, a
        64 MiB artifact would hold the server's GIL for tens of milliseconds, and every
        resolve with it (:mod:`capevo.registry.uploads`)."""
        upload, total = secrets.token_hex(16), len(data)
        view = memoryview(data)

        def send(offset: int) -> tuple[zenoh.Sample, int]:
            chunk = bytes(view[offset : offset + PART_BYTES])
            end = offset + len(chunk)
            part = UploadPart(upload, offset, total)
            header = encode_command("publish", name=name, spec=spec if part.first else None, actor=who, part=part)
            # the last part's reply waits for the whole artifact to be hashed and made durable
            timeout = self._timeout + (total if end == total else len(chunk)) * SECONDS_PER_BYTE
            return self._query(self._cmd_key("publish"), payload=chunk, attachment=header, timeout=timeout), end

        *parts, last = range(0, total, PART_BYTES)
        for offset in parts:
            sample, end = send(offset)
            received = decode_reply(sample.payload.to_bytes(), _received, what="publish part")
            if received != end:
                raise CapevoError(f"the registry acknowledged {received} bytes of upload {upload}, not {end}")
        sample, _ = send(last)
        return decode_reply(sample.payload.to_bytes(), EcmVersion.from_dict, what="publish")

    def promote(
        self,
        name: str,
        version: int,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion:
        """Make candidate ``version`` active. Raises Conflict, IllegalTransition, NotFound, Forbidden."""
        return self._command(
            "promote",
            name=name,
            version=version,
            expected_active=expected_active,
            reason=reason,
            actor=self._who(actor),
        )

    def rollback(
        self,
        name: str,
        to: int | None = None,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion:
        """Re-activate superseded version ``to`` (default: the previous active one)."""
        return self._command(
            "rollback", name=name, to=to, expected_active=expected_active, reason=reason, actor=self._who(actor)
        )

    def deprecate(self, name: str, version: int, *, reason: str = "", actor: str | None = None) -> EcmVersion:
        """Retire a version that is not active."""
        return self._command("deprecate", name=name, version=version, reason=reason, actor=self._who(actor))

    def reject(self, name: str, version: int, *, reason: str = "", actor: str | None = None) -> EcmVersion:
        """Mark a candidate as rejected by its gate."""
        return self._command("reject", name=name, version=version, reason=reason, actor=self._who(actor))

    def record_gate(
        self,
        name: str,
        version: int,
        evidence: Mapping[str, Any],
        *,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion:
        """Attach gate evidence to a candidate."""
        return self._command(
            "gate", name=name, version=version, evidence=evidence, reason=reason, actor=self._who(actor)
        )

    # --- events -----------------------------------------------------------------------
    def subscribe_events(self, name: str, callback: EventCallback) -> EventSubscription:
        """Call ``callback(event, record)`` for each change committed to ``name`` (``"*"``: every ECM).

        The callback runs on a Zenoh thread; exceptions it raises are logged and dropped.
        Events of one ECM carry increasing ``event.seq``; concurrent commits may arrive out of order.

        Raises:
            Invalid: bad name. Unavailable: the client is closed.
        """
        key = self._keys.events(name)
        if self._closed:
            raise Unavailable("this registry client is closed")

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                event, record = decode_event(sample.payload.to_bytes())
            except CapevoError as exc:
                log.warning("dropping malformed event on %s: %s", sample.key_expr, exc)
                return
            try:
                callback(event, record)
            except Exception:
                # The callback is the caller's code on Zenoh's thread; it must not kill delivery.
                log.exception("event callback failed for %s seq %d", event.name, event.seq)

        try:
            subscriber = self._session.declare_subscriber(key, on_sample)
        except zenoh.ZError as exc:
            raise Unavailable(f"cannot subscribe to {key}: {_first_line(exc)}") from None
        subscription = EventSubscription(subscriber, self._forget)
        with self._lock:
            self._subscriptions.append(subscription)
        return subscription

    def _forget(self, subscription: EventSubscription) -> None:
        with self._lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)

    # --- lifetime ---------------------------------------------------------------------
    def close(self) -> None:
        """End subscriptions and close the session. Idempotent."""
        if self._closed:
            return
        with self._lock:
            subscriptions = list(self._subscriptions)
        for subscription in subscriptions:
            subscription.close()
        self._closed = True
        try:
            self._session.close()
        except zenoh.ZError as exc:
            log.debug("closing the Zenoh session: %s", exc)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({list(self._connect)!r}, namespace={self.namespace!r})"


def _json_object(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise TypeError(f"expected a JSON object, got {type(value).__name__}")
    return value


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /", 1)[0].splitlines()[0][:300] if text else type(exc).__name__
