"""The registry server: a :class:`LocalRegistry` served over Zenoh from a router-mode session.

Run it with ``python -m capevo.registry.service --root DIR [--listen EP]... [--connect EP]...
[--namespace NS] [--config FILE]``; it prints one ``READY {json}`` line on stdout once it
serves, and shuts down cleanly on SIGTERM or SIGINT.

Queries arrive on Zenoh callback threads and are handed to a bounded worker pool, so a slow
64 MB publish does not hold up reads. Each query gets exactly one reply: the answer, or an
error reply carrying :meth:`CapevoError.to_payload`.

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

from capevo.errors import CapevoError, Invalid, TooLarge, Unavailable
from capevo.records import AuditEvent, EcmVersion
from capevo.registry.keys import COMMANDS, Keys, Route
from capevo.registry.local import DEFAULT_MAX_ARTIFACT_BYTES, LocalRegistry
from capevo.registry.server_config import ServerConfig, access_control_for, load_server_config, write_dictionary
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

PROTOCOL_VERSION = 1
DEFAULT_WORKERS = 8
DEFAULT_MAX_IN_FLIGHT = 64
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
    """What a handler may use: the registry and the server's limits."""

    registry: LocalRegistry
    keys: Keys
    max_artifact_bytes: int
    secured: bool


ReadHandler = Callable[[Context, Route, dict[str, int]], Answer]
CommandHandler = Callable[[LocalRegistry, dict[str, Any], bytes], EcmVersion]
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
def handle_publish(reg: LocalRegistry, f: dict[str, Any], artifact: bytes) -> EcmVersion:
    return reg.publish(f["name"], artifact, f["spec"], actor=f["actor"])


@command_handler("promote")
def handle_promote(reg: LocalRegistry, f: dict[str, Any], artifact: bytes) -> EcmVersion:
    return reg.promote(
        f["name"], f["version"], expected_active=f["expected_active"], reason=f["reason"], actor=f["actor"]
    )


@command_handler("rollback")
def handle_rollback(reg: LocalRegistry, f: dict[str, Any], artifact: bytes) -> EcmVersion:
    return reg.rollback(f["name"], f["to"], expected_active=f["expected_active"], reason=f["reason"], actor=f["actor"])


@command_handler("deprecate")
def handle_deprecate(reg: LocalRegistry, f: dict[str, Any], artifact: bytes) -> EcmVersion:
    return reg.deprecate(f["name"], f["version"], reason=f["reason"], actor=f["actor"])


@command_handler("reject")
def handle_reject(reg: LocalRegistry, f: dict[str, Any], artifact: bytes) -> EcmVersion:
    return reg.reject(f["name"], f["version"], reason=f["reason"], actor=f["actor"])


@command_handler("gate")
def handle_gate(reg: LocalRegistry, f: dict[str, Any], artifact: bytes) -> EcmVersion:
    return reg.record_gate(f["name"], f["version"], f["evidence"], reason=f["reason"], actor=f["actor"])


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
    op = ctx.keys.parse_cmd_key(key)
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
        if size > ctx.max_artifact_bytes:
            raise TooLarge(
                f"artifact is {size} bytes; the limit is {ctx.max_artifact_bytes}",
                details={"size": size, "limit": ctx.max_artifact_bytes},
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
    record = COMMAND_HANDLERS[op](ctx.registry, fields, artifact)
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


class _Dispatcher:
    """Hands queries from Zenoh's callback threads to a bounded worker pool."""

    def __init__(self, ctx: Context, *, workers: int, max_in_flight: int) -> None:
        self._ctx = ctx
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="capevo-registry")
        self._slots = threading.BoundedSemaphore(max_in_flight)
        self._max_in_flight = max_in_flight

    def on_read(self, query: zenoh.Query) -> None:
        self._submit(query, answer_read)

    def on_command(self, query: zenoh.Query) -> None:
        self._submit(query, answer_command)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=False)

    def _submit(self, query: zenoh.Query, answer: Callable[[Context, zenoh.Query], Answer]) -> None:
        if not self._slots.acquire(blocking=False):
            _reply_once(query, Unavailable(f"registry busy: {self._max_in_flight} requests in flight; retry shortly"))
            return
        try:
            self._pool.submit(self._run, query, answer)
        except RuntimeError:  # pool already shut down
            self._slots.release()
            _reply_once(query, Unavailable("registry is shutting down"))

    def _run(self, query: zenoh.Query, answer: Callable[[Context, zenoh.Query], Answer]) -> None:
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
            self._slots.release()


def _describe(query: zenoh.Query) -> str:
    try:
        return str(query.selector)
    except zenoh.ZError:
        return "<query>"


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
        registry = LocalRegistry(
            root, actor=REMOTE_ACTOR, max_artifact_bytes=limit, listeners=[EventPublisher(session, keys)]
        )
        stack.callback(registry.close)
        ctx = Context(registry=registry, keys=keys, max_artifact_bytes=limit, secured=secured)
        dispatcher = _Dispatcher(ctx, workers=workers, max_in_flight=max_in_flight)
        stack.callback(dispatcher.shutdown)
        for key_expr in keys.read_roots():
            queryable = session.declare_queryable(key_expr, dispatcher.on_read)
            stack.callback(queryable.undeclare)
        commands = session.declare_queryable(keys.cmd_tree, dispatcher.on_command)
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
