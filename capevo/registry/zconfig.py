"""Build ``zenoh.Config`` objects for the registry router and its clients from typed arguments.

Only this module knows Zenoh's configuration paths; everything else passes typed values.

Invariants:
1. Multicast scouting is off unless asked for; gossip stays Zenoh's default.
2. Every endpoint is checked by Zenoh itself while building; a bad one raises
   :class:`Invalid` naming it, never a raw ``zenoh.ZError``.
3. A client config always has ``mode: client`` and at least one connect endpoint.
4. Passwords only ever go into the config object, never into log lines or ``repr``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from capevo.errors import Invalid

DEFAULT_LISTEN: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
# Zenoh's own default is 1 GiB; a router that serves untrusted clients should not reassemble
# more than it will accept. The registry sets this from its artifact limit.
ZENOH_DEFAULT_MAX_MESSAGE_SIZE = 1 << 30


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohSettings:
    """Everything the registry ever sets in a Zenoh config.

    Args:
        mode: ``router`` (the registry) or ``client`` (everyone else).
        listen: Endpoints to listen on, e.g. ``tcp/127.0.0.1:7447``.
        connect: Endpoints to connect to (routers to join, or the registry for a client).
        multicast_scouting: Discover peers by UDP multicast; off in tests and by default.
        user, password: This node's own credentials (``transport/auth/usrpwd``).
        dictionary_file: File of ``user:password`` lines a router checks clients against.
        access_control: The ``access_control`` block (see :mod:`capevo.registry.server_config`).
        max_message_size: Largest message Zenoh reassembles from fragments, in bytes.
        scouting_delay_ms: How long opening waits to discover others before serving; Zenoh's
            default (500 ms) is pure start-up delay for a router with nothing to discover.
    """

    mode: str
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    user: str | None = None
    password: str | None = field(default=None, repr=False)
    dictionary_file: Path | None = None
    access_control: Mapping[str, Any] | None = None
    max_message_size: int | None = None
    scouting_delay_ms: int | None = None


def build_config(settings: ZenohSettings) -> zenoh.Config:
    """The ``zenoh.Config`` for ``settings``.

    Raises:
        Invalid: unknown mode, bad endpoint, half a credential pair, or a config Zenoh refuses.
    """
    if settings.mode not in ("router", "client", "peer"):
        raise Invalid(f"zenoh mode must be router, client or peer, got {settings.mode!r}", details={"field": "mode"})
    if (settings.user is None) != (settings.password is None):
        raise Invalid("zenoh credentials need both user and password", details={"field": "user"})
    config = zenoh.Config()
    _insert(config, "mode", settings.mode)
    _insert(config, "scouting/multicast/enabled", settings.multicast_scouting)
    _insert(config, "listen/endpoints", list(settings.listen), what="listen endpoint")
    _insert(config, "connect/endpoints", list(settings.connect), what="connect endpoint")
    usrpwd: dict[str, Any] = {}
    if settings.user is not None:
        usrpwd.update(user=settings.user, password=settings.password)
    if settings.dictionary_file is not None:
        usrpwd["dictionary_file"] = str(settings.dictionary_file)
    if usrpwd:
        _insert(config, "transport/auth/usrpwd", usrpwd, what="usrpwd authentication", secret=True)
    if settings.access_control is not None:
        _insert(config, "access_control", dict(settings.access_control), what="access_control")
    if settings.max_message_size is not None:
        _insert(config, "transport/link/rx/max_message_size", int(settings.max_message_size))
    if settings.scouting_delay_ms is not None:
        _insert(config, "scouting/delay", int(settings.scouting_delay_ms))
    return config


def router_config(
    *,
    listen: Sequence[str] = DEFAULT_LISTEN,
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    user: str | None = None,
    password: str | None = None,
    dictionary_file: Path | None = None,
    access_control: Mapping[str, Any] | None = None,
    max_message_size: int | None = None,
) -> zenoh.Config:
    """Config of the registry's own session: a router other nodes connect to.

    Raises:
        Invalid: see :func:`build_config`; also when there is nothing to listen on.
    """
    if not listen:
        raise Invalid("a registry router needs at least one listen endpoint", details={"field": "listen"})
    return build_config(
        ZenohSettings(
            mode="router",
            listen=tuple(listen),
            connect=tuple(connect),
            multicast_scouting=multicast_scouting,
            user=user,
            password=password,
            dictionary_file=dictionary_file,
            access_control=access_control,
            max_message_size=max_message_size,
            # Nothing to discover without peers to join or multicast: serve at once.
            scouting_delay_ms=0 if not connect and not multicast_scouting else None,
        )
    )


def client_config(
    *,
    connect: Sequence[str],
    user: str | None = None,
    password: str | None = None,
    multicast_scouting: bool = False,
) -> zenoh.Config:
    """Config of a registry client: client mode, talks only to the routers in ``connect``.

    Raises:
        Invalid: no endpoint, bad endpoint, half a credential pair.
    """
    if isinstance(connect, str):
        connect = [connect]
    if not connect:
        raise Invalid("a registry client needs at least one connect endpoint", details={"field": "connect"})
    return build_config(
        ZenohSettings(
            mode="client",
            connect=tuple(connect),
            user=user,
            password=password,
            multicast_scouting=multicast_scouting,
        )
    )


def config_from_flags(
    *,
    mode: str,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    user: str | None = None,
    password: str | None = None,
    multicast_scouting: bool = False,
) -> zenoh.Config:
    """The config the CLI flags ``--mode/--listen/--connect/--user/--password/--multicast`` describe.

    Comma-separated endpoint lists are accepted as well as repeated flags.

    Raises:
        Invalid: see :func:`build_config`.
    """
    return build_config(
        ZenohSettings(
            mode=mode,
            listen=split_endpoints(listen),
            connect=split_endpoints(connect),
            user=user,
            password=password,
            multicast_scouting=multicast_scouting,
        )
    )


def split_endpoints(values: Sequence[str] | str | None) -> tuple[str, ...]:
    """Flatten repeated and comma-separated endpoint flags, dropping blanks."""
    if values is None:
        return ()
    if isinstance(values, str):
        values = [values]
    return tuple(part.strip() for value in values for part in value.split(",") if part.strip())


def _insert(config: zenoh.Config, path: str, value: Any, *, what: str | None = None, secret: bool = False) -> None:
    try:
        config.insert_json5(path, json.dumps(value))
    except zenoh.ZError as exc:
        # The usrpwd error could echo the password back; say only where it went wrong.
        reason = "" if secret else f": {_first_line(str(exc))}"
        raise Invalid(f"bad {what or path} {'' if secret else value!r}{reason}", details={"field": path}) from None


def _first_line(text: str) -> str:
    return text.split(" at /", 1)[0].splitlines()[0][:300] if text else text
