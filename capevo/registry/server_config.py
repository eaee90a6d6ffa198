"""The registry server's config file (YAML) and what Zenoh makes of it: usrpwd + access control.

Example::

    namespace: capevo                 # key prefix of everything the registry serves
    listen: [tcp/0.0.0.0:7447]        # where clients connect
    connect: []                       # other Zenoh routers (zenohd) to join
    multicast_scouting: false
    max_artifact_bytes: 268435456     # optional; largest artifact accepted
    users:                            # none -> the registry runs OPEN (no auth, no ACL)
      alice:     {password: "change-me", roles: [operator]}
      learner-1: {password_env: CAPEVO_LEARNER_PW, roles: [learner]}
      dashboard: {password_file: secrets/dashboard.pw, roles: [reader]}
    trusted_nodes:                    # Zenoh nodes granted roles by Zenoh id (e.g. a joined zenohd)
      - {zid: 1f2e3d4c5b6a7980, roles: [reader]}
    credentials:                      # this registry's own login on the routers in `connect`
      user: registry
      password_env: CAPEVO_REGISTRY_PW

Authentication and authorisation are Zenoh's own: users become ``transport/auth/usrpwd``
dictionary lines (a 0600 file in a private temp dir) and roles become ``access_control``
rules, subjects (by username) and policies with ``default_permission: deny``. A wrong or
missing password cannot open a session at all; a user whose role lacks a command has that
query dropped by the router before the registry ever sees it.

Commands are bound to the authenticated user by the key they arrive on: user ``alice``
sends ``<ns>/cmd/<op>/@alice`` (a Zenoh verbatim chunk, which no wildcard matches), and
only alice is granted that key, only for the commands her roles allow. The registry takes
the audit actor from the key, never from the request body.

Trusted nodes (``trusted_nodes``) are other routers, such as a zenohd the registry joins.
Traffic through them carries the node's identity, not the identity of whoever sent it, so
a node may hold only roles without commands (``reader``, ``runtime``); its users read
through it, and log in to the registry itself to change anything.

Invariants:
1. Every rejection is an :class:`Invalid` whose message starts with the dotted path of the
   offending field (``users.alice.roles[0]``); parsing raises nothing else for any text.
2. ``access_control_for`` grants each user exactly the commands its roles list (see
   :class:`Role`); every role can read, subscribe to events and check liveliness; nothing
   else is allowed.
3. No users configured means no ``access_control`` and no dictionary (the registry is open).
4. The dictionary file is created with mode 0600 in a directory only its owner can enter,
   and passwords never appear in ``repr`` or error messages.
5. Every command rule names one user's own keys ``<ns>/cmd/<op>/@<user>``; no subject is
   granted another user's command key, and no trusted node is granted any command key.
"""

from __future__ import annotations

import os
import re
import stat
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from capevo.errors import Invalid
from capevo.registry.keys import COMMANDS, DEFAULT_NAMESPACE, USER_PATTERN, Keys, validate_namespace
from capevo.registry.zconfig import DEFAULT_LISTEN, split_endpoints

ZID_PATTERN = re.compile(r"[0-9a-f]{1,32}")
MAX_PASSWORD_CHARS = 1024
MAX_CONFIG_BYTES = 1024 * 1024


@dataclass(frozen=True, slots=True, kw_only=True)
class Role:
    """A named set of registry commands a user may run; every role may read."""

    name: str
    commands: frozenset[str]
    description: str
    serves_runtime: bool = False
    """May serve ``<ns>/runtime/**``: runtime workers' evaluate/adopted queryables and liveliness."""
    vouches: bool = False
    """May publish ``origin: manual`` (code the runtime trusts to run outside the sandbox) and
    name an ``on_behalf_of`` beside itself in the audit trail."""


ROLES: dict[str, Role] = {}


def register_role(role: Role) -> Role:
    """Add ``role`` to :data:`ROLES`.

    Raises:
        Invalid: duplicate name or a command that does not exist.
    """
    if role.name in ROLES:
        raise Invalid(f"role {role.name!r} is already registered")
    unknown = sorted(role.commands - set(COMMANDS))
    if unknown:
        raise Invalid(f"role {role.name!r}: unknown commands {unknown}; commands are {', '.join(COMMANDS)}")
    ROLES[role.name] = role
    return role


def make_role(name: str) -> Role:
    """The registered role called ``name``.

    Raises:
        Invalid: listing the valid role names.
    """
    try:
        return ROLES[name]
    except (KeyError, TypeError):
        raise Invalid(f"unknown role {name!r}; valid roles: {', '.join(sorted(ROLES))}") from None


register_role(Role(name="reader", commands=frozenset(), description="read keys, events and liveliness"))
register_role(
    Role(
        name="learner", commands=frozenset({"publish", "gate"}), description="reader + publish candidates, record gates"
    )
)
register_role(
    Role(
        name="operator",
        commands=frozenset(COMMANDS),
        description="every command; publishes trusted (origin: manual) code; may act on behalf of a named actor",
        vouches=True,
    )
)
register_role(
    Role(
        name="runtime",
        commands=frozenset(),
        description="reader + serve runtime-worker keys (evaluate, adopted, liveliness)",
        serves_runtime=True,
    )
)


@dataclass(frozen=True, slots=True, kw_only=True)
class UserEntry:
    name: str
    password: str = field(repr=False)
    roles: tuple[str, ...]


@dataclass(frozen=True, slots=True, kw_only=True)
class NodeEntry:
    zid: str
    roles: tuple[str, ...]


@dataclass(frozen=True, slots=True, kw_only=True)
class Credentials:
    user: str
    password: str = field(repr=False)


@dataclass(frozen=True, slots=True, kw_only=True)
class ServerConfig:
    """Parsed registry config file; see the module docstring for the YAML."""

    namespace: str = DEFAULT_NAMESPACE
    listen: tuple[str, ...] = DEFAULT_LISTEN
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    max_artifact_bytes: int | None = None
    users: tuple[UserEntry, ...] = ()
    trusted_nodes: tuple[NodeEntry, ...] = ()
    credentials: Credentials | None = None

    @property
    def secured(self) -> bool:
        """True when Zenoh authentication and access control are on."""
        return bool(self.users)

    def commands_of(self, user: str) -> frozenset[str]:
        """The commands ``user``'s roles allow (none for an unknown user)."""
        return frozenset(op for u in self.users if u.name == user for r in u.roles for op in ROLES[r].commands)

    def vouches(self, user: str) -> bool:
        """Whether one of ``user``'s roles vouches (see :attr:`Role.vouches`)."""
        return any(ROLES[r].vouches for u in self.users if u.name == user for r in u.roles)


_TOP_FIELDS = frozenset(
    {
        "namespace",
        "listen",
        "connect",
        "multicast_scouting",
        "max_artifact_bytes",
        "users",
        "trusted_nodes",
        "credentials",
    }
)


def load_server_config(path: str | os.PathLike[str], *, env: Mapping[str, str] | None = None) -> ServerConfig:
    """Read and validate a config file; ``password_file`` paths are relative to its directory.

    Raises:
        Invalid: unreadable file or any field error (see :func:`parse_server_config`).
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise Invalid(f"<config>: cannot read {p}: {exc.strerror}", details={"field": "<config>"}) from None
    return parse_server_config(text, env=env, base_dir=p.parent)


def parse_server_config(
    text: str | bytes, *, env: Mapping[str, str] | None = None, base_dir: Path | None = None
) -> ServerConfig:
    """Parse config YAML.

    Args:
        text: The YAML.
        env: Where ``password_env`` is looked up; defaults to ``os.environ``.
        base_dir: Directory relative ``password_file`` paths start from (default: cwd).

    Raises:
        Invalid: whose message starts with the offending field's dotted path.
    """
    if len(text) > MAX_CONFIG_BYTES:
        raise Invalid(f"<config>: {len(text)} bytes; the limit is {MAX_CONFIG_BYTES}", details={"field": "<config>"})
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise Invalid(f"<config>: not valid YAML: {exc}", details={"field": "<config>"}) from None
    except (ValueError, RecursionError) as exc:
        raise Invalid(f"<config>: not valid YAML: {exc}", details={"field": "<config>"}) from None
    return server_config_from_dict({} if doc is None else doc, env=env, base_dir=base_dir)


def server_config_from_dict(
    doc: object, *, env: Mapping[str, str] | None = None, base_dir: Path | None = None
) -> ServerConfig:
    """Validate an already-parsed config document. Raises Invalid like :func:`parse_server_config`."""
    env = os.environ if env is None else env
    d = _mapping(doc, "<config>")
    _no_unknown(d, _TOP_FIELDS, "")
    namespace = d.get("namespace", DEFAULT_NAMESPACE)
    try:
        validate_namespace(namespace)
    except Invalid as exc:
        raise _at("namespace", exc.message) from None
    max_bytes = d.get("max_artifact_bytes")
    if max_bytes is not None and (isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 1):
        raise _at("max_artifact_bytes", f"must be a positive integer, got {max_bytes!r}")
    users = tuple(_user(name, entry, env, base_dir) for name, entry in _mapping(d.get("users") or {}, "users").items())
    nodes = tuple(_node(i, entry) for i, entry in enumerate(_sequence(d.get("trusted_nodes") or [], "trusted_nodes")))
    if nodes and not users:
        raise _at("trusted_nodes", "needs users: access control is only on when users are configured")
    creds_doc = d.get("credentials")
    credentials = None
    if creds_doc is not None:
        c = _mapping(creds_doc, "credentials")
        _no_unknown(c, frozenset({"user", "password", "password_env", "password_file"}), "credentials")
        credentials = Credentials(
            user=_username(c.get("user"), "credentials.user"),
            password=_password(c, "credentials", env, base_dir),
        )
    multicast = d.get("multicast_scouting", False)
    if not isinstance(multicast, bool):
        raise _at("multicast_scouting", f"must be true or false, got {multicast!r}")
    listen = _endpoints(d.get("listen", list(DEFAULT_LISTEN)), "listen")
    if not listen:
        raise _at("listen", "needs at least one endpoint")
    return ServerConfig(
        namespace=namespace,
        listen=listen,
        connect=_endpoints(d.get("connect", []), "connect"),
        multicast_scouting=multicast,
        max_artifact_bytes=max_bytes,
        users=users,
        trusted_nodes=nodes,
        credentials=credentials,
    )


def access_control_for(config: ServerConfig) -> dict[str, Any] | None:
    """The Zenoh ``access_control`` block that enforces the configured roles; None when open.

    Rules (``default_permission: deny``):

    * ``capevo-read-in``: ingress ``query``, ``declare_subscriber``,
      ``declare_liveliness_subscriber``, ``liveliness_query`` on the read keys, events and
      liveliness keys;
    * ``capevo-read-out``: egress ``reply``, ``put``, ``delete``, ``liveliness_token``,
      ``declare_queryable``, ``declare_subscriber``, ``declare_liveliness_subscriber``
      under ``<ns>/**`` (what a reader must receive);
    * ``capevo-runtime-serve``: ``declare_queryable``, ``liveliness_token``, ``reply`` and
      ``query`` on ``<ns>/runtime/**``, for roles that serve runtime workers;
    * ``capevo-cmd-<user>``: ingress ``query``, and egress ``reply`` and
      ``declare_queryable``, on ``<ns>/cmd/<op>/@<user>`` for each command the user's roles
      allow; one rule, one subject and one policy per user with any command.

    Each role gets a subject listing its users (and one listing its trusted node zids) and
    a policy tying it to the read rules (and the runtime rule for roles serving runtime
    workers).
    """
    if not config.secured:
        return None
    ns = config.namespace
    rules: list[dict[str, Any]] = [
        {
            "id": "capevo-read-in",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["query", "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": [
                f"{ns}/ecm",
                f"{ns}/ecm/**",
                f"{ns}/set",
                f"{ns}/verify",
                f"{ns}/history",
                f"{ns}/info",
                f"{ns}/events/**",
                f"{ns}/alive/**",
                f"{ns}/runtime/**",
            ],
        },
        {
            "id": "capevo-read-out",
            "permission": "allow",
            "flows": ["egress"],
            "messages": [
                "reply",
                "put",
                "delete",
                "liveliness_token",
                "declare_queryable",
                "declare_subscriber",
                "declare_liveliness_subscriber",
            ],
            "key_exprs": [f"{ns}/**"],
        },
    ]
    rules.append(
        {
            # A worker declares its queryables and token, answers, and receives the queries.
            "id": "capevo-runtime-serve",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ["declare_queryable", "liveliness_token", "reply", "query"],
            "key_exprs": [f"{ns}/runtime/**"],
        }
    )
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    keys = Keys(ns)
    for user in config.users:
        allowed = config.commands_of(user.name)
        if not allowed:
            continue
        own_keys = [keys.cmd(op, user.name) for op in COMMANDS if op in allowed]
        # The registry replies (egress) on the key the query came in on; ``<ns>/**`` in the
        # read rules does not cover it, because ``**`` never matches a verbatim chunk.
        rules.append(
            {"id": f"capevo-cmd-{user.name}-in", **_ALLOW_IN_QUERY, "key_exprs": own_keys},
        )
        rules.append(
            {"id": f"capevo-cmd-{user.name}-out", **_ALLOW_OUT_REPLY, "key_exprs": own_keys},
        )
        subjects.append({"id": f"capevo-user-{user.name}", "usernames": [user.name]})
        policies.append(
            {
                "id": f"capevo-cmd-{user.name}",
                "rules": [f"capevo-cmd-{user.name}-in", f"capevo-cmd-{user.name}-out"],
                "subjects": [f"capevo-user-{user.name}"],
            }
        )
    for role_name in sorted(ROLES):
        role = ROLES[role_name]
        subject_ids = []
        users = sorted(u.name for u in config.users if role_name in u.roles)
        if users:
            subjects.append({"id": f"capevo-users-{role_name}", "usernames": users})
            subject_ids.append(f"capevo-users-{role_name}")
        zids = sorted(n.zid for n in config.trusted_nodes if role_name in n.roles)
        if zids:
            subjects.append({"id": f"capevo-nodes-{role_name}", "zids": zids})
            subject_ids.append(f"capevo-nodes-{role_name}")
        if subject_ids:
            role_rules = ["capevo-read-in", "capevo-read-out"]
            if role.serves_runtime:
                role_rules.append("capevo-runtime-serve")
            policies.append({"id": f"capevo-role-{role_name}", "rules": role_rules, "subjects": subject_ids})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


_ALLOW_IN_QUERY: dict[str, Any] = {"permission": "allow", "flows": ["ingress"], "messages": ["query"]}
_ALLOW_OUT_REPLY: dict[str, Any] = {
    "permission": "allow",
    "flows": ["egress"],
    "messages": ["reply", "declare_queryable"],
}


def write_dictionary(config: ServerConfig, directory: Path | None = None) -> Path:
    """Write the usrpwd dictionary (``user:password`` lines) for ``config``'s users.

    Args:
        config: Must be secured (have users).
        directory: Where to write; default a fresh private temp dir. The caller removes it.

    Returns:
        The file path, mode 0600.

    Raises:
        Invalid: the config has no users.
    """
    if not config.secured:
        raise Invalid("users: none configured, so there is no password dictionary to write")
    directory = Path(tempfile.mkdtemp(prefix="capevo-usrpwd-")) if directory is None else directory
    path = directory / "usrpwd.txt"
    # O_EXCL + 0600 at creation: the secret is never readable by others, not even briefly.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, stat.S_IRUSR | stat.S_IWUSR)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.writelines(f"{u.name}:{u.password}\n" for u in config.users)
    return path


# --- field parsers -------------------------------------------------------------------------


def _at(field: str, message: str) -> Invalid:
    return Invalid(f"{field}: {message}", details={"field": field})


def _mapping(value: object, field: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise _at(field, f"must be a mapping, got {type(value).__name__}")
    for key in value:
        if not isinstance(key, str):
            raise _at(field, f"keys must be strings, got {key!r}")
    return value


def _sequence(value: object, field: str) -> list[Any]:
    if not isinstance(value, list):
        raise _at(field, f"must be a list, got {type(value).__name__}")
    return value


def _no_unknown(d: Mapping[str, Any], known: frozenset[str], prefix: str) -> None:
    unknown = sorted(set(d) - known)
    if unknown:
        field = f"{prefix}.{unknown[0]}" if prefix else unknown[0]
        raise _at(field, f"unknown field; fields are {', '.join(sorted(known))}")


def _endpoints(value: object, field: str) -> tuple[str, ...]:
    items = [value] if isinstance(value, str) else _sequence(value, field)
    for i, item in enumerate(items):
        if not isinstance(item, str) or "/" not in item:
            raise _at(f"{field}[{i}]", f"must be an endpoint like tcp/127.0.0.1:7447, got {item!r}")
    return split_endpoints(items)


def _username(value: object, field: str) -> str:
    if not isinstance(value, str) or not USER_PATTERN.fullmatch(value):
        raise _at(field, f"user name must be 1-64 of letters, digits, '.', '_', '@', '-', got {value!r}")
    return value


def _password(d: Mapping[str, Any], field: str, env: Mapping[str, str], base_dir: Path | None) -> str:
    sources = [k for k in ("password", "password_env", "password_file") if k in d]
    if len(sources) != 1:
        raise _at(field, "give exactly one of password, password_env, password_file")
    source = sources[0]
    raw = d[source]
    if not isinstance(raw, str) or not raw:
        raise _at(f"{field}.{source}", "must be a non-empty string")
    if source == "password":
        password = raw
    elif source == "password_env":
        if raw not in env:
            raise _at(f"{field}.password_env", f"environment variable {raw} is not set")
        password = env[raw]
    else:
        path = Path(raw) if base_dir is None or Path(raw).is_absolute() else base_dir / raw
        try:
            password = path.read_text(encoding="utf-8").rstrip("\r\n")
        except (OSError, UnicodeDecodeError) as exc:
            raise _at(f"{field}.password_file", f"cannot read {path}: {exc}") from None
    # The dictionary is line-based and Zenoh splits at the first ':' of the line.
    if not password or len(password) > MAX_PASSWORD_CHARS or not password.isprintable() or password != password.strip():
        raise _at(
            f"{field}.{source}",
            f"password must be 1-{MAX_PASSWORD_CHARS} printable characters without leading or trailing spaces",
        )
    return password


def _roles(value: object, field: str) -> tuple[str, ...]:
    items = _sequence(value, field)
    if not items:
        raise _at(field, f"needs at least one role; valid roles: {', '.join(sorted(ROLES))}")
    for i, item in enumerate(items):
        try:
            make_role(item)
        except Invalid as exc:
            raise _at(f"{field}[{i}]", exc.message) from None
    return tuple(dict.fromkeys(items))


def _user(name: str, entry: object, env: Mapping[str, str], base_dir: Path | None) -> UserEntry:
    field = f"users.{name}"
    _username(name, field)
    d = _mapping(entry, field)
    _no_unknown(d, frozenset({"password", "password_env", "password_file", "roles"}), field)
    if "roles" not in d:
        raise _at(f"{field}.roles", "missing")
    return UserEntry(name=name, password=_password(d, field, env, base_dir), roles=_roles(d["roles"], f"{field}.roles"))


def _node(index: int, entry: object) -> NodeEntry:
    field = f"trusted_nodes[{index}]"
    d = _mapping(entry, field)
    _no_unknown(d, frozenset({"zid", "roles"}), field)
    zid = d.get("zid")
    if not isinstance(zid, str) or not ZID_PATTERN.fullmatch(zid):
        raise _at(f"{field}.zid", f"must be a Zenoh id (1-32 lowercase hex digits), got {zid!r}")
    if "roles" not in d:
        raise _at(f"{field}.roles", "missing")
    roles = _roles(d["roles"], f"{field}.roles")
    for i, name in enumerate(roles):
        if ROLES[name].commands:
            raise _at(
                f"{field}.roles[{i}]",
                f"role {name!r} runs commands, and a node relays other people's traffic: the registry could not "
                "tell who sent a command through it. Give the node reader or runtime, and let its users log in "
                "to the registry to change anything",
            )
    return NodeEntry(zid=zid, roles=roles)
