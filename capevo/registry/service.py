"""The registry server: a :class:`LocalRegistry` served over Zenoh from a router-mode session.

Run it with ``python -m capevo.registry.service --root DIR [--listen EP]... [--connect EP]...
[--namespace NS] [--config FILE]``; it prints one ``READY {json}`` line on stdout once it
serves, and shuts down cleanly on SIGTERM or SIGINT.

The hot reads (a version or ``active``, the ECM list, the current capability set) are
answered on the Zenoh callback thread that received them, from the in-memory
:class:`~capevo.registry.read_cache.ReadCache`: no thread hop, no transaction, no encoding,
and nothing that waits for a write. Every other query is handed to a bounded worker pool,
so a slow 64 MB publish does not hold up reads, and the client sends a large artifact in
parts (:mod:`capevo.registry.uploads`), so taking its bytes never holds the GIL for long.
Heavy reads (``verify``, which re-hashes every blob, and the whole audit chain) get their own
small lane: a flood of them is refused ``busy`` there and cannot take the slots that resolves
and commands need. Each query gets exactly one reply: the answer, or an error reply carrying
:meth:`CapevoError.to_payload`.

Who made a change is Zenoh's word, not the request's: a secured registry serves commands
only on ``<ns>/cmd/<op>/@<user>``, which access control grants to ``<user>`` alone, and
records that user as the actor (:class:`~capevo.records.Auth` ``user``). A body ``actor``
that differs is kept as ``on_behalf_of`` for operators and dropped for everyone else. An
open registry records the claimed actor, marked ``auth: open``. Only an operator may
publish ``origin: manual``, the origin the runtime trusts to run outside its sandbox.

Invariants:
1. Every query the server receives gets exactly one reply (success or error) unless the
   reply itself cannot be sent; no request content can make a handler raise out of the
   worker, so the server keeps serving after any malformed request.
2. A request is checked (key, parameters, size, JSON, fields) before the registry is
   touched; a refused request changes nothing.
3. Every committed change is published on ``<ns>/events/<name>`` after its commit.
4. The liveliness token ``<ns>/alive/registry`` exists exactly while queries are served:
   declared after the queryables, undeclared before them.
5. With users configured, Zenoh's usrpwd + access control are on; without, the server logs
   that it runs open.
6. On a secured registry every mutation's actor is the authenticated user its key names;
   nothing in the request body can change it, and a publish of ``origin: manual`` by a user
   whose roles do not vouch (see :class:`~capevo.registry.server_config.Role`) is refused
   ``forbidden`` before anything is written.
7. A heavy read never occupies an ordinary slot: at most ``heavy_max_in_flight`` of them
   run or wait at once, and beyond that they are refused ``unavailable`` ("busy").
8. A read answered from memory replies the same bytes the SQLite path would, for a state
   that includes every commit acknowledged before the query arrived, of this server or any
   other process writing the root. What memory does not hold (errors included) goes the
   SQLite path. The cache catches up after each commit before the commit's event is
   published and before the command is answered.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import sys
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from capevo.errors import CapevoError, Forbidden, Invalid, TooLarge, Unavailable
from capevo.records import Attribution, AuditEvent, Auth, EcmVersion, Origin
from capevo.registry.keys import COMMANDS, CommandRoute, Keys, Route
from capevo.registry.local import DB_FILENAME, DEFAULT_MAX_ARTIFACT_BYTES, LocalRegistry
from capevo.registry.read_cache import MEMORY_ENDPOINTS, ReadCache
from capevo.registry.server_config import ServerConfig, access_control_for, load_server_config, write_dictionary
from capevo.registry.uploads import Uploads
from capevo.registry.wire import (
    JSON_ENCODING,
    MAX_JSON_BYTES,
    OCTETS_ENCODING,
    ArtifactMeta,
    decode_command,
    dumps,
    encode_event,
    read_parameters,
)
from capevo.registry.zconfig import router_config
from capevo.shutdown import stop_on_signals

log = logging.getLogger("capevo.registry.service")

# 2: a secured registry takes commands on <ns>/cmd/<op>/@<user> only.
PROTOCOL_VERSION = 2
DEFAULT_WORKERS = 8
DEFAULT_MAX_IN_FLIGHT = 64
DEFAULT_HEAVY_WORKERS = 1
DEFAULT_HEAVY_MAX_IN_FLIGHT = 4
MEMO_ROUTES = 4096
"""Hot-read keys whose parsed route the server keeps (one per ECM version asked for, roughly)."""
# The actor recorded when a remote request names none.
REMOTE_ACTOR = "remote"
READY_PREFIX = "READY "


@dataclass(frozen=True, slots=True, kw_only=True)
class ServeInfo:
    """What a running server tells its ``ready`` callback."""

    root: str
    namespace: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    zid: str
    secured: bool
    max_artifact_bytes: int
    pid: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "root": self.root,
            "namespace": self.namespace,
            "listen": list(self.listen),
            "connect": list(self.connect),
            "zid": self.zid,
            "secured": self.secured,
            "max_artifact_bytes": self.max_artifact_bytes,
            "pid": self.pid,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Answer:
    """A successful reply: bytes plus their encoding and an optional attachment."""

    payload: bytes
    encoding: str = JSON_ENCODING
    attachment: bytes | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class Context:
    """What a handler may use: the registry, the server's limits, its users' roles and the
    uploads in progress."""

    registry: LocalRegistry
    keys: Keys
    max_artifact_bytes: int
    config: ServerConfig
    uploads: Uploads

    @property
    def secured(self) -> bool:
        return self.config.secured


ReadHandler = Callable[[Context, Route, dict[str, int]], Answer]
CommandHandler = Callable[[LocalRegistry, dict[str, Any], bytes, Attribution], EcmVersion]
READ_HANDLERS: dict[str, ReadHandler] = {}
COMMAND_HANDLERS: dict[str, CommandHandler] = {}


def read_handler(endpoint: str) -> Callable[[ReadHandler], ReadHandler]:
    """Register the handler of one read endpoint (see :data:`capevo.registry.keys.READ_ENDPOINTS`)."""

    def register(fn: ReadHandler) -> ReadHandler:
        READ_HANDLERS[endpoint] = fn
        return fn

    return register


def command_handler(op: str) -> Callable[[CommandHandler], CommandHandler]:
    """Register the handler of one command (see :data:`capevo.registry.keys.COMMANDS`)."""

    def register(fn: CommandHandler) -> CommandHandler:
        COMMAND_HANDLERS[op] = fn
        return fn

    return register


def _json(value: Any) -> Answer:
    return Answer(payload=dumps(value))


# --- read handlers -------------------------------------------------------------------------


@read_handler("list")
def handle_list(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json([s.to_dict() for s in ctx.registry.list_ecms()])


@read_handler("ecm")
def handle_ecm(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json(ctx.registry.get_ecm(str(route.name)).to_dict())


@read_handler("version")
def handle_version(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json(ctx.registry.get_version(str(route.name), route.version).to_dict())


@read_handler("artifact")
def handle_artifact(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    # Resolve "active" once, so the bytes and the attachment describe the same version.
    record = ctx.registry.get_version(str(route.name), route.version)
    data = ctx.registry.get_artifact(record.name, record.version)
    return Answer(payload=data, encoding=OCTETS_ENCODING, attachment=ArtifactMeta.of(record).encode())


@read_handler("history")
def handle_history(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json([e.to_dict() for e in ctx.registry.history(route.name)])


@read_handler("set")
def handle_set(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json(ctx.registry.capability_set(params.get("revision")).to_dict())


@read_handler("verify")
def handle_verify(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json(ctx.registry.verify().to_dict())


@read_handler("info")
def handle_info(ctx: Context, route: Route, params: dict[str, int]) -> Answer:
    return _json(
        {
            "protocol": PROTOCOL_VERSION,
            "namespace": ctx.keys.namespace,
            "max_artifact_bytes": ctx.max_artifact_bytes,
            "max_json_bytes": MAX_JSON_BYTES,
            "secured": ctx.secured,
            "commands": list(COMMANDS),
        }
    )


# --- command handlers ----------------------------------------------------------------------


@command_handler("publish")
def handle_publish(reg: LocalRegistry, f: dict[str, Any], artifact: bytes, who: Attribution) -> EcmVersion:
    return reg.publish(f["name"], artifact, f["spec"], actor=who)


@command_handler("promote")
def handle_promote(reg: LocalRegistry, f: dict[str, Any], artifact: bytes, who: Attribution) -> EcmVersion:
    return reg.promote(f["name"], f["version"], expected_active=f["expected_active"], reason=f["reason"], actor=who)


@command_handler("rollback")
def handle_rollback(reg: LocalRegistry, f: dict[str, Any], artifact: bytes, who: Attribution) -> EcmVersion:
    return reg.rollback(f["name"], f["to"], expected_active=f["expected_active"], reason=f["reason"], actor=who)


@command_handler("deprecate")
def handle_deprecate(reg: LocalRegistry, f: dict[str, Any], artifact: bytes, who: Attribution) -> EcmVersion:
    return reg.deprecate(f["name"], f["version"], reason=f["reason"], actor=who)


@command_handler("reject")
def handle_reject(reg: LocalRegistry, f: dict[str, Any], artifact: bytes, who: Attribution) -> EcmVersion:
    return reg.reject(f["name"], f["version"], reason=f["reason"], actor=who)


@command_handler("gate")
def handle_gate(reg: LocalRegistry, f: dict[str, Any], artifact: bytes, who: Attribution) -> EcmVersion:
    return reg.record_gate(f["name"], f["version"], f["evidence"], reason=f["reason"], actor=who)


# --- who is asking -------------------------------------------------------------------------


def attribute(config: ServerConfig, route: CommandRoute, claimed: str | None) -> Attribution:
    """Who a command is recorded against: the user its key names, never the body's ``actor``.

    Args:
        config: The server's users and roles.
        route: The parsed command key.
        claimed: The request's ``actor`` field.

    Raises:
        Forbidden: a secured registry got a command without a user, or from a user whose
            roles do not allow it (access control should have dropped it already).
        Invalid: an open registry got a per-user key.
    """
    if not config.secured:
        if route.user is not None:
            raise Invalid(
                f"this registry is open: send {route.op} on <ns>/cmd/{route.op}, without a user chunk",
                details={"field": "key"},
            )
        return Attribution(actor=claimed or REMOTE_ACTOR, auth=Auth.OPEN)
    if route.user is None or route.op not in config.commands_of(route.user):
        who = "no user" if route.user is None else f"user {route.user!r}"
        raise Forbidden(f"{route.op}: {who} may not run it on this secured registry", details={"user": route.user})
    vouched = claimed if claimed not in (None, route.user) and config.vouches(route.user) else None
    return Attribution(actor=route.user, auth=Auth.USER, on_behalf_of=vouched)


def check_origin(config: ServerConfig, who: Attribution, origin: Origin) -> None:
    """Refuse ``origin: manual`` from a secured registry's user whose roles do not vouch.

    ``manual`` is what :class:`capevo.runtime.ecm.trust.TrustPolicy` runs in-process, with
    no sandbox; it is granted by the registry, never declared by a learner.

    Raises:
        Forbidden: naming the user and the origins they may use.
    """
    if origin is not Origin.MANUAL or not config.secured or config.vouches(who.actor):
        return
    others = ", ".join(o.value for o in Origin if o is not Origin.MANUAL)
    raise Forbidden(
        f"publish: origin 'manual' marks code the runtime trusts to run outside its sandbox; only an operator "
        f"may publish it, and user {who.actor!r} is not one (publish as {others})",
        details={"field": "spec.origin", "user": who.actor},
    )


# --- request decoding ----------------------------------------------------------------------


def _payload_bytes(query: zenoh.Query) -> bytes:
    payload = query.payload
    return b"" if payload is None else payload.to_bytes()


def _attachment_bytes(query: zenoh.Query) -> bytes | None:
    attachment = query.attachment
    return None if attachment is None else attachment.to_bytes()


def answer_read(ctx: Context, query: zenoh.Query) -> Answer:
    """Route a read query to its handler.

    Raises:
        Invalid: bad key or parameters, or a payload/attachment on a read.
        CapevoError: whatever the registry raises (NotFound, ...).
    """
    key = str(query.key_expr)
    route = ctx.keys.parse_read_key(key)
    params = read_parameters(route.endpoint, list(query.parameters))
    if query.payload is not None and len(query.payload) > 0:
        raise Invalid(f"{key}: read queries take no payload", details={"field": "<payload>"})
    if query.attachment is not None:
        raise Invalid(f"{key}: read queries take no attachment", details={"field": "<attachment>"})
    return READ_HANDLERS[route.endpoint](ctx, route, params)


def answer_command(ctx: Context, query: zenoh.Query) -> Answer:
    """Decode, check and run one command query.

    Raises:
        Invalid, TooLarge: a malformed or oversize request.
        CapevoError: whatever the registry raises (Conflict, NotFound, ...).
    """
    key = str(query.key_expr)
    route = ctx.keys.parse_cmd(key)
    op = route.op
    read_parameters(f"cmd/{op}", list(query.parameters))
    size = 0 if query.payload is None else len(query.payload)
    if op == "publish":
        attachment = _attachment_bytes(query)
        if attachment is None:
            raise Invalid(
                "publish: missing header; send the JSON header in the query attachment and the artifact as payload",
                details={"field": "<attachment>"},
            )
        fields = decode_command(op, attachment)
        # a part names the whole artifact's size: refuse a too large one at its first part
        claimed = size if fields["part"] is None else max(size, fields["part"].total)
        if claimed > ctx.max_artifact_bytes:
            raise TooLarge(
                f"artifact is {claimed} bytes; the limit is {ctx.max_artifact_bytes}",
                details={"size": claimed, "limit": ctx.max_artifact_bytes},
            )
        artifact = _payload_bytes(query)
    else:
        if query.attachment is not None:
            raise Invalid(
                f"{op}: unexpected attachment; send the JSON request as payload", details={"field": "<attachment>"}
            )
        if size > MAX_JSON_BYTES:
            raise TooLarge(f"{op} request: {size} bytes; the limit is {MAX_JSON_BYTES}", details={"size": size})
        fields = decode_command(op, _payload_bytes(query))
        artifact = b""
    who = attribute(ctx.config, route, fields["actor"])
    if op == "publish" and fields["spec"] is not None:
        check_origin(ctx.config, who, fields["spec"].origin)  # before the first part is staged
    if op == "publish" and fields["part"] is not None:
        # A part in the server's hands costs the GIL a fraction of a millisecond; the whole
        # artifact in one payload would stall every resolve for tens (uploads.py).
        part = fields["part"]
        done = ctx.uploads.add(who.actor, fields["name"], part, artifact, fields["spec"])
        if done is None:
            return _json({"upload": part.upload, "received": part.offset + len(artifact)})
        return _json(ctx.registry.publish_written(done.name, done.writer, done.spec, actor=who).to_dict())
    record = COMMAND_HANDLERS[op](ctx.registry, fields, artifact, who)
    return _json(record.to_dict())


# --- the server ----------------------------------------------------------------------------


class EventPublisher:
    """:class:`capevo.registry.local.EventListener` that puts each commit on ``<ns>/events/<name>``."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self._session = session
        self._keys = keys

    def on_event(self, event: AuditEvent, record: EcmVersion) -> None:
        self._session.put(
            self._keys.events(event.name),
            encode_event(event, record),
            encoding=JSON_ENCODING,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )


def is_heavy_read(keys: Keys, key: str) -> bool:
    """Whether a read key asks for work that grows with the whole registry (``verify``, the
    whole audit chain); a key that does not parse is not heavy (its handler refuses it)."""
    try:
        route = keys.parse_read_key(key)
    except Invalid:
        return False
    return route.endpoint == "verify" or (route.endpoint == "history" and route.name is None)


class _Lane:
    """A worker pool with a bounded number of queries running or waiting in it."""

    def __init__(self, what: str, *, workers: int, max_in_flight: int) -> None:
        self.what = what
        self.pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"capevo-registry-{what}")
        self.slots = threading.BoundedSemaphore(max_in_flight)
        self.max_in_flight = max_in_flight


class _Dispatcher:
    """Answers hot reads from memory on Zenoh's callback threads and hands every other query
    to the ordinary or the heavy lane."""

    def __init__(
        self,
        ctx: Context,
        cache: ReadCache,
        *,
        workers: int,
        max_in_flight: int,
        heavy_workers: int,
        heavy_max_in_flight: int,
    ) -> None:
        self._ctx = ctx
        self._cache = cache
        self._ordinary = _Lane("requests", workers=workers, max_in_flight=max_in_flight)
        self._heavy = _Lane(
            "heavy reads (verify, whole history)", workers=heavy_workers, max_in_flight=heavy_max_in_flight
        )
        # Hot-read keys already parsed: a cold parse was about a tenth of the server's CPU per
        # resolve (issue 21). Only well-formed memory keys are kept; dropped whole when full.
        self._routes: dict[str, Route] = {}

    def on_read(self, query: zenoh.Query) -> None:
        key_expr = query.key_expr
        key = str(key_expr)
        payload = self._from_memory(key, query)
        if payload is not None:
            _reply_from_memory(query, key_expr, payload)
            return
        heavy = is_heavy_read(self._ctx.keys, key)
        self._submit(self._heavy if heavy else self._ordinary, query, answer_read)

    def _from_memory(self, key: str, query: zenoh.Query) -> bytes | None:
        """The reply of a well-formed hot read, from the read cache; None sends it the SQLite way.

        Runs on a Zenoh callback thread, so it must never block: it parses the key (once: the
        route is kept), loads the store's commit word and, only when it moved, asks SQLite's
        ``data_version`` on the cache's own connection (a reader, which in WAL mode never waits
        for a writer), and looks the bytes up. A malformed query, a
        miss or a failing cache returns None, and the lane's handler answers it, errors included.
        """
        try:
            route = self._routes.get(key)
            if route is None:
                route = self._ctx.keys.parse_read_key(key)
                if route.endpoint not in MEMORY_ENDPOINTS:
                    return None
                if len(self._routes) >= MEMO_ROUTES:
                    self._routes.clear()
                self._routes[key] = route
            if query.attachment is not None:
                return None
            if query.payload is not None and len(query.payload) > 0:
                return None
            parameters = query.parameters
            params = {} if parameters.is_empty() else read_parameters(route.endpoint, list(parameters))
            return self._cache.current().reply(route, params)
        except Invalid:
            return None
        except Exception:
            # Invariant 1: the SQLite path still answers; the cache's failure is only logged.
            log.exception("read cache failed on %s; answering from SQLite", key)
            return None

    def on_command(self, query: zenoh.Query) -> None:
        self._submit(self._ordinary, query, answer_command)

    def shutdown(self) -> None:
        for lane in (self._ordinary, self._heavy):
            lane.pool.shutdown(wait=True, cancel_futures=False)

    def _submit(self, lane: _Lane, query: zenoh.Query, answer: Callable[[Context, zenoh.Query], Answer]) -> None:
        if not lane.slots.acquire(blocking=False):
            _reply_once(query, Unavailable(f"registry busy: {lane.max_in_flight} {lane.what} in flight; retry shortly"))
            return
        try:
            lane.pool.submit(self._run, lane, query, answer)
        except RuntimeError:  # pool already shut down
            lane.slots.release()
            _reply_once(query, Unavailable("registry is shutting down"))

    def _run(self, lane: _Lane, query: zenoh.Query, answer: Callable[[Context, zenoh.Query], Answer]) -> None:
        try:
            try:
                result: Answer | CapevoError = answer(self._ctx, query)
            except CapevoError as exc:
                result = exc
            except Exception:
                # Invariant 1: a bug must cost one request, never the server.
                log.exception("internal error answering %s", _describe(query))
                result = CapevoError("internal error in the registry; see its log")
            _reply_once(query, result)
        finally:
            lane.slots.release()


def _describe(query: zenoh.Query) -> str:
    try:
        return str(query.selector)
    except zenoh.ZError:
        return "<query>"


# Parsed once: hot reads reply with it thousands of times a second.
_JSON = zenoh.Encoding(JSON_ENCODING)


def _reply_from_memory(query: zenoh.Query, key_expr: zenoh.KeyExpr, payload: bytes) -> None:
    """:func:`_reply_once` for a hot read's bytes, without its other cases: this runs on every
    resolve, and each step on the answering thread keeps Zenoh's threads waiting (issue 21)."""
    try:
        with query:
            query.reply(key_expr, payload, encoding=_JSON)
    except zenoh.ZError as exc:
        log.warning("could not reply to %s: %s", _describe(query), exc)


def _reply_once(query: zenoh.Query, result: Answer | CapevoError) -> None:
    """Send the one reply of ``query`` and finalise it (a dropped query ends the client's wait)."""
    try:
        with query:
            if isinstance(result, CapevoError):
                if not isinstance(result, (Invalid, TooLarge)):
                    log.info("%s -> %s", _describe(query), result)
                query.reply_err(result.to_payload(), encoding=JSON_ENCODING)
            else:
                query.reply(query.key_expr, result.payload, encoding=result.encoding, attachment=result.attachment)
    except zenoh.ZError as exc:
        log.warning("could not reply to %s: %s", _describe(query), exc)


def command_keys(config: ServerConfig, keys: Keys) -> list[str]:
    """The command keys the server serves: every user's own (secured), or ``<ns>/cmd/**`` (open).

    A verbatim ``@<user>`` chunk matches no wildcard, so a secured server declares each
    key it serves exactly.
    """
    if not config.secured:
        return [keys.cmd_tree]
    return [keys.cmd(op, u.name) for u in config.users for op in COMMANDS if op in config.commands_of(u.name)]


def _notify_ready(ready: Callable[[ServeInfo], Any] | threading.Event | None, info: ServeInfo) -> None:
    if ready is None:
        return
    if isinstance(ready, threading.Event):
        ready.set()
    else:
        ready(info)


def zenoh_max_message_size(max_artifact_bytes: int) -> int:
    """What Zenoh may reassemble: twice the artifact limit plus headroom.

    Oversize requests up to this size still reach the registry and get a ``too_large`` reply;
    Zenoh drops anything bigger before the registry sees it (the client then times out).
    """
    return 2 * max_artifact_bytes + 2 * MAX_JSON_BYTES + (1 << 20)


def serve(
    root: str | os.PathLike[str],
    *,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    namespace: str | None = None,
    config: ServerConfig | None = None,
    ready: Callable[[ServeInfo], Any] | threading.Event | None = None,
    stop: threading.Event | None = None,
    multicast_scouting: bool | None = None,
    max_artifact_bytes: int | None = None,
    workers: int = DEFAULT_WORKERS,
    max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
    heavy_workers: int = DEFAULT_HEAVY_WORKERS,
    heavy_max_in_flight: int = DEFAULT_HEAVY_MAX_IN_FLIGHT,
    handle_signals: bool = True,
) -> None:
    """Serve the registry at ``root`` over Zenoh until ``stop`` is set or SIGTERM/SIGINT arrives.

    Explicit arguments win over ``config``, which wins over the defaults
    (``tcp/127.0.0.1:7447``, namespace ``capevo``, multicast scouting off).

    Args:
        root: Registry directory (see :class:`LocalRegistry`).
        listen: Endpoints to listen on.
        connect: Zenoh routers (e.g. zenohd) to join.
        namespace: Key prefix.
        config: Users, roles, credentials and the settings above (see :mod:`server_config`).
        ready: Called with a :class:`ServeInfo` (or set, if an Event) once queries are served.
        stop: Set it to shut down; a private one is used when None.
        multicast_scouting: Discover peers by UDP multicast.
        max_artifact_bytes: Largest artifact accepted.
        workers: Threads answering queries.
        max_in_flight: Queries accepted at once; more get an ``unavailable`` "busy" reply.
        heavy_workers: Threads answering heavy reads (``verify``, the whole history).
        heavy_max_in_flight: Heavy reads accepted at once, apart from ``max_in_flight``.
        handle_signals: Install SIGTERM/SIGINT handlers (main thread only).

    Raises:
        Invalid: bad endpoint, namespace or config.
        Unavailable: the Zenoh session cannot open (e.g. the port is taken) or ``root`` is unusable.
    """
    cfg = config if config is not None else ServerConfig()
    keys = Keys(namespace if namespace is not None else cfg.namespace)
    listen_eps = tuple(listen) if listen is not None else cfg.listen
    connect_eps = tuple(connect) if connect is not None else cfg.connect
    multicast = cfg.multicast_scouting if multicast_scouting is None else multicast_scouting
    limit = next(v for v in (max_artifact_bytes, cfg.max_artifact_bytes, DEFAULT_MAX_ARTIFACT_BYTES) if v is not None)
    stop = stop if stop is not None else threading.Event()
    secured = cfg.secured
    with contextlib.ExitStack() as stack:
        dictionary = None
        if secured:
            dictionary = write_dictionary(cfg)
            stack.callback(shutil.rmtree, dictionary.parent, ignore_errors=True)
            roles = sorted({r for u in cfg.users for r in u.roles})
            log.info("access control on: %d users, roles %s", len(cfg.users), ", ".join(roles))
        else:
            log.warning(
                "no users configured: the registry is OPEN; anyone who can reach %s may read and mutate it",
                ", ".join(listen_eps),
            )
        zconf = router_config(
            listen=listen_eps,
            connect=connect_eps,
            multicast_scouting=multicast,
            user=cfg.credentials.user if cfg.credentials else None,
            password=cfg.credentials.password if cfg.credentials else None,
            dictionary_file=dictionary,
            access_control=access_control_for(cfg) if secured else None,
            max_message_size=zenoh_max_message_size(limit),
        )
        try:
            session = zenoh.open(zconf)
        except zenoh.ZError as exc:
            raise Unavailable(f"cannot open the registry's Zenoh session on {', '.join(listen_eps)}: {exc}") from None
        stack.callback(session.close)
        registry = LocalRegistry(root, actor=REMOTE_ACTOR, max_artifact_bytes=limit)
        stack.callback(registry.close)
        cache = ReadCache(registry.root / DB_FILENAME)
        stack.callback(cache.close)
        # The cache catches up before the event goes out, so a subscriber that resolves on
        # an event finds the change; both run before the command's reply (invariant 8).
        registry.add_listener(cache)
        registry.add_listener(EventPublisher(session, keys))
        uploads = Uploads(registry.artifact_writer, max_artifact_bytes=limit)
        stack.callback(uploads.close)
        ctx = Context(registry=registry, keys=keys, max_artifact_bytes=limit, config=cfg, uploads=uploads)
        dispatcher = _Dispatcher(
            ctx,
            cache,
            workers=workers,
            max_in_flight=max_in_flight,
            heavy_workers=heavy_workers,
            heavy_max_in_flight=heavy_max_in_flight,
        )
        stack.callback(dispatcher.shutdown)
        for key_expr in keys.read_roots():
            queryable = session.declare_queryable(key_expr, dispatcher.on_read)
            stack.callback(queryable.undeclare)
        for key_expr in command_keys(cfg, keys):
            commands = session.declare_queryable(key_expr, dispatcher.on_command)
            stack.callback(commands.undeclare)
        token = session.liveliness().declare_token(keys.alive())
        stack.callback(token.undeclare)
        stack.enter_context(stop_on_signals(stop, enabled=handle_signals, what="registry"))
        info = ServeInfo(
            root=str(Path(root).resolve()),
            namespace=keys.namespace,
            listen=listen_eps,
            connect=connect_eps,
            zid=str(session.zid()),
            secured=secured,
            max_artifact_bytes=limit,
            pid=os.getpid(),
        )
        log.info("serving registry %s as %s on %s (zid %s)", info.root, keys.namespace, ", ".join(listen_eps), info.zid)
        _notify_ready(ready, info)
        # A timed wait keeps the main thread responsive to signals.
        while not stop.wait(0.5):
            pass
        log.info("registry %s shutting down", info.root)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m capevo.registry.service``: serve until SIGTERM/SIGINT. Returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m capevo.registry.service", description=__doc__.split("\n")[0])
    parser.add_argument("--root", required=True, help="registry directory")
    parser.add_argument("--listen", action="append", help="endpoint to listen on (repeatable)")
    parser.add_argument("--connect", action="append", help="Zenoh router to join (repeatable)")
    parser.add_argument("--namespace", help="key prefix (default: capevo)")
    parser.add_argument("--config", help="registry config YAML (users, roles, ...)")
    parser.add_argument("--multicast-scouting", action="store_true", default=None, help="enable UDP multicast scouting")
    parser.add_argument("--max-artifact-bytes", type=int, help="largest artifact accepted")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ...")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    def print_ready(info: ServeInfo) -> None:
        print(READY_PREFIX + json.dumps(info.to_dict()), flush=True)

    try:
        config = load_server_config(args.config) if args.config else None
        serve(
            args.root,
            listen=args.listen,
            connect=args.connect,
            namespace=args.namespace,
            config=config,
            ready=print_ready,
            multicast_scouting=args.multicast_scouting,
            max_artifact_bytes=args.max_artifact_bytes,
        )
    except Invalid as exc:
        print(f"capevo registry: {exc}", file=sys.stderr)
        return 2
    except CapevoError as exc:
        print(f"capevo registry: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
