"""The registry's Zenoh key space: building keys and parsing the keys a query arrives on.

Key space, under a namespace ``<ns>`` (default ``capevo``)::

    <ns>/ecm                          list of ECMs (EcmSummary list)
    <ns>/ecm/<name>                   EcmDetail
    <ns>/ecm/<name>/active            EcmVersion of the active version
    <ns>/ecm/<name>/<k>               EcmVersion k
    <ns>/ecm/<name>/<k>/artifact      artifact bytes of version k
    <ns>/ecm/<name>/active/artifact   artifact bytes of the active version
    <ns>/ecm/<name>/history           audit events of <name>
    <ns>/history                      the whole audit chain, every ECM
    <ns>/set[?revision=R]             CapabilitySet (now, or at revision R)
    <ns>/verify                       VerifyReport (read-only integrity check)
    <ns>/info                         limits and settings a client needs (JSON object)
    <ns>/cmd/<op>                     mutations of an open registry: publish promote rollback
                                      deprecate reject gate
    <ns>/cmd/<op>/@<user>             mutations of a secured registry, by Zenoh-authenticated <user>
    <ns>/events/<name>                committed changes, published after each commit
    <ns>/alive/registry               liveliness token of a running registry

Invariants:
1. ``parse_read_key(ns, build(...))`` returns the route the builder meant, for every
   builder in :class:`Keys` that addresses a queryable.
2. ``parse_read_key`` and ``parse_cmd`` raise only :class:`Invalid`; a key with a
   wildcard, a bad ECM name, a non-canonical version number or an unknown word is refused,
   never guessed at.
3. Every key :class:`Keys` builds is a valid, wildcard-free Zenoh key expression (except
   ``events("*")``, the one deliberate wildcard for subscribers).
4. ``parse_cmd(build.cmd(op, user)) == CommandRoute(op=op, user=user)``. The user chunk is
   a Zenoh *verbatim* chunk (``@<user>``): no wildcard (``*``, ``**``) in a query, a
   queryable or an access-control rule ever matches it, so only a rule naming that exact
   user grants it, and a name or an ECM can never be mistaken for it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from capevo.errors import Invalid
from capevo.records.names import validate_name, validate_version

DEFAULT_NAMESPACE = "capevo"
NAMESPACE_PATTERN = re.compile(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*")
MAX_NAMESPACE_LENGTH = 128
# 18 digits keeps a version inside a signed 64-bit SQLite integer.
MAX_VERSION_DIGITS = 18
# What a registry user may be called; Zenoh's usrpwd dictionary splits its lines at ':'.
USER_PATTERN = re.compile(r"[A-Za-z0-9._@-]{1,64}")
USER_CHUNK_PREFIX = "@"

COMMANDS: tuple[str, ...] = ("publish", "promote", "rollback", "deprecate", "reject", "gate")
READ_ENDPOINTS: tuple[str, ...] = ("list", "ecm", "version", "artifact", "history", "set", "verify", "info")
ACTIVE = "active"
ARTIFACT = "artifact"
HISTORY = "history"


def validate_user(user: object, field: str = "user") -> str:
    """Return ``user`` if it is a valid registry user name (1-64 of letters, digits, ``._@-``).

    Raises:
        Invalid: naming ``field``.
    """
    if not isinstance(user, str) or not USER_PATTERN.fullmatch(user):
        raise Invalid(
            f"{field}: user name must be 1-64 of letters, digits, '.', '_', '@', '-', got {user!r}",
            details={"field": field},
        )
    return user


def validate_namespace(namespace: object) -> str:
    """Return ``namespace`` if it is a wildcard-free key prefix such as ``capevo`` or ``lab/robot1``.

    Raises:
        Invalid: naming what is wrong with it.
    """
    if not isinstance(namespace, str):
        raise Invalid(f"namespace must be a string, got {type(namespace).__name__}", details={"field": "namespace"})
    if len(namespace) > MAX_NAMESPACE_LENGTH or not NAMESPACE_PATTERN.fullmatch(namespace):
        raise Invalid(
            f"namespace {namespace!r} must be 1-{MAX_NAMESPACE_LENGTH} characters of letters, digits, '_', '.', '-' "
            "in '/'-separated parts, with no wildcard",
            details={"field": "namespace"},
        )
    if any(part in {".", ".."} for part in namespace.split("/")):
        raise Invalid(f"namespace {namespace!r} may not contain '.' or '..' parts", details={"field": "namespace"})
    return namespace


@dataclass(frozen=True, slots=True, kw_only=True)
class Route:
    """What a read key asks for: ``endpoint`` is one of :data:`READ_ENDPOINTS`.

    ``version`` None with endpoint ``version`` or ``artifact`` means the active version.
    """

    endpoint: str
    name: str | None = None
    version: int | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class CommandRoute:
    """What a command key names: the command and, on a secured registry, who sent it.

    ``user`` is None on the open form ``<ns>/cmd/<op>``.
    """

    op: str
    user: str | None = None


@dataclass(frozen=True, slots=True)
class Keys:
    """Builds every key of one namespace.

    Args:
        namespace: Key prefix; validated by :func:`validate_namespace`.

    Raises:
        Invalid: for a bad namespace.
    """

    namespace: str = DEFAULT_NAMESPACE

    def __post_init__(self) -> None:
        validate_namespace(self.namespace)

    # --- queryables (what the server declares) ------------------------------------------
    @property
    def ecm_tree(self) -> str:
        """Matches ``<ns>/ecm`` and everything below it (``**`` includes zero chunks)."""
        return f"{self.namespace}/ecm/**"

    @property
    def cmd_tree(self) -> str:
        return f"{self.namespace}/cmd/**"

    # --- concrete keys ------------------------------------------------------------------
    def ecm_list(self) -> str:
        return f"{self.namespace}/ecm"

    def ecm(self, name: str) -> str:
        return f"{self.namespace}/ecm/{validate_name(name)}"

    def version(self, name: str, version: int | None = None) -> str:
        """``<ns>/ecm/<name>/<k>``, or ``.../active`` when ``version`` is None."""
        chunk = ACTIVE if version is None else str(validate_version(version))
        return f"{self.ecm(name)}/{chunk}"

    def artifact(self, name: str, version: int | None = None) -> str:
        return f"{self.version(name, version)}/{ARTIFACT}"

    def history(self, name: str) -> str:
        """Key of ``name``'s events; :meth:`history_all` is every ECM's."""
        return f"{self.ecm(name)}/{HISTORY}"

    def history_all(self) -> str:
        return f"{self.namespace}/{HISTORY}"

    def capability_set(self) -> str:
        return f"{self.namespace}/set"

    def verify(self) -> str:
        return f"{self.namespace}/verify"

    def info(self) -> str:
        return f"{self.namespace}/info"

    def read_roots(self) -> tuple[str, ...]:
        """Key expressions of every read queryable the server declares."""
        return (self.ecm_tree, self.capability_set(), self.verify(), self.history_all(), self.info())

    def cmd(self, op: str, user: str | None = None) -> str:
        """``<ns>/cmd/<op>``, or ``<ns>/cmd/<op>/@<user>`` for a secured registry's ``user``.

        Raises:
            Invalid: unknown command or bad user name.
        """
        if op not in COMMANDS:
            raise Invalid(f"unknown command {op!r}; valid commands: {', '.join(COMMANDS)}", details={"field": "op"})
        key = f"{self.namespace}/cmd/{op}"
        return key if user is None else f"{key}/{USER_CHUNK_PREFIX}{validate_user(user)}"

    def events(self, name: str = "*") -> str:
        """Key of ``name``'s change events; ``"*"`` subscribes to every ECM."""
        return f"{self.namespace}/events/" + ("*" if name == "*" else validate_name(name))

    def alive(self) -> str:
        return f"{self.namespace}/alive/registry"

    # --- parsing ------------------------------------------------------------------------
    def parse_read_key(self, key: str) -> Route:
        """The :class:`Route` a concrete read key names.

        Raises:
            Invalid: wildcard, key outside the namespace, bad name or version, unknown word.
        """
        rest = _strip_namespace(self.namespace, key)
        parts = rest.split("/")
        if parts == ["set"]:
            return Route(endpoint="set")
        if parts == ["verify"]:
            return Route(endpoint="verify")
        if parts == [HISTORY]:
            return Route(endpoint="history")
        if parts == ["info"]:
            return Route(endpoint="info")
        if parts[0] != "ecm":
            raise _unknown_key(key)
        if len(parts) == 1:
            return Route(endpoint="list")
        name = validate_name(parts[1])
        if len(parts) == 2:
            return Route(endpoint="ecm", name=name)
        if len(parts) == 3 and parts[2] == HISTORY:
            return Route(endpoint="history", name=name)
        version = _parse_version_chunk(parts[2], key)
        if len(parts) == 3:
            return Route(endpoint="version", name=name, version=version)
        if len(parts) == 4 and parts[3] == ARTIFACT:
            return Route(endpoint="artifact", name=name, version=version)
        raise _unknown_key(key)

    def parse_cmd(self, key: str) -> CommandRoute:
        """The command (and user) a ``<ns>/cmd/<op>`` or ``<ns>/cmd/<op>/@<user>`` key names.

        Raises:
            Invalid: wildcard, key outside ``<ns>/cmd``, unknown command, bad user chunk.
        """
        rest = _strip_namespace(self.namespace, key)
        parts = rest.split("/")
        if len(parts) not in (2, 3) or parts[0] != "cmd":
            raise _unknown_key(key)
        if parts[1] not in COMMANDS:
            raise Invalid(
                f"unknown command {parts[1]!r}; valid commands: {', '.join(COMMANDS)}",
                details={"field": "key", "key": key},
            )
        if len(parts) == 2:
            return CommandRoute(op=parts[1])
        chunk = parts[2]
        if not chunk.startswith(USER_CHUNK_PREFIX):
            raise _unknown_key(key)
        return CommandRoute(op=parts[1], user=validate_user(chunk[len(USER_CHUNK_PREFIX) :], "key"))

    def parse_cmd_key(self, key: str) -> str:
        """The command a command key names (see :meth:`parse_cmd`). Raises Invalid."""
        return self.parse_cmd(key).op


def _strip_namespace(namespace: str, key: str) -> str:
    if "*" in key:
        raise Invalid(
            f"key {key!r} has a wildcard; the registry answers one concrete key per query",
            details={"field": "key", "key": key},
        )
    prefix = namespace + "/"
    if not key.startswith(prefix):
        raise Invalid(f"key {key!r} is outside namespace {namespace!r}", details={"field": "key", "key": key})
    return key[len(prefix) :]


def _parse_version_chunk(chunk: str, key: str) -> int | None:
    if chunk == ACTIVE:
        return None
    # Only canonical decimal: '007', '+7', ' 7' and '٧' (int() accepts Unicode digits) are refused.
    if not (chunk.isascii() and chunk.isdigit()) or len(chunk) > MAX_VERSION_DIGITS or str(int(chunk)) != chunk:
        raise Invalid(
            f"key {key!r}: {chunk!r} is neither 'active', 'history' nor a canonical version number",
            details={"field": "version", "key": key},
        )
    return int(chunk)


def _unknown_key(key: str) -> Invalid:
    return Invalid(
        f"unknown registry key {key!r}; see the key space in capevo.registry.keys", details={"field": "key", "key": key}
    )
