"""The ``capevo`` command line: one click group, shared registry options and output helpers.

Every registry command talks to either a local registry directory (``--root``) or a running
registry over Zenoh (``--connect``), prints a human table by default and JSON with ``--json``.

Exit codes (stable; scripts may match on them):

====  ======================  ====================================================
code  error code              meaning
====  ======================  ====================================================
0                             success
1     internal                unexpected failure (a bug, or an OS error)
2     (click usage)           bad command line: unknown option, missing argument
3     invalid                 bad input: name, descriptor, version, file to read
4     not_found               no such ECM, version, revision or registry root
5     conflict                lost compare-and-swap (``--expected-active``), duplicate
6     illegal_transition      lifecycle forbids the move (e.g. promote a rejected version)
7     forbidden               access control refused the request
8     corrupt                 blob hash or audit chain mismatch; ``registry verify`` problems
9     timeout                 the registry did not answer in time
10    unavailable             the registry is not reachable
11    too_large               artifact or request above a limit
12    safety_violation        governance rejected an action
13    sandbox_violation       untrusted code broke the sandbox rules
14    identity_violation      the persistent agent changed
130                           interrupted (Ctrl-C)
====  ======================  ====================================================

Invariants:
1. A :class:`CapevoError` raised by any command becomes exactly one line
   ``error [code]: message`` on stderr and the exit code in :data:`EXIT_CODES`; never a
   traceback.
2. Exactly one of ``--root`` / ``--connect`` selects the registry. A value given on the
   command line beats one from the environment, which beats the default; two at the same
   level are refused with :class:`Invalid`.
3. ``--json`` output on stdout is a single JSON document; human output never goes to
   stdout when ``--json`` is given.
4. Passwords are never printed, not even in error messages.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import functools
import importlib
import json
import logging
import os
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

import click
from click.core import ParameterSource
from rich import box
from rich.console import Console
from rich.table import Table

from capevo.errors import CapevoError, ErrorCode, Invalid, NotFound
from capevo.registry.api import Registry

DEFAULT_ROOT = "./capevo-data"
DEFAULT_NAMESPACE = "capevo"
DEFAULT_TIMEOUT_S = 10.0

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_CODES: dict[ErrorCode, int] = {
    ErrorCode.INTERNAL: 1,
    ErrorCode.INVALID: 3,
    ErrorCode.NOT_FOUND: 4,
    ErrorCode.CONFLICT: 5,
    ErrorCode.ILLEGAL_TRANSITION: 6,
    ErrorCode.FORBIDDEN: 7,
    ErrorCode.CORRUPT: 8,
    ErrorCode.TIMEOUT: 9,
    ErrorCode.UNAVAILABLE: 10,
    ErrorCode.TOO_LARGE: 11,
    ErrorCode.SAFETY_VIOLATION: 12,
    ErrorCode.SANDBOX_VIOLATION: 13,
    ErrorCode.IDENTITY_VIOLATION: 14,
}

F = TypeVar("F", bound=Callable[..., Any])


def exit_code_for(err: CapevoError) -> int:
    """The process exit code for ``err`` (see the table in this module's docstring)."""
    return EXIT_CODES.get(err.code, EXIT_INTERNAL)


def error_line(err: CapevoError) -> str:
    """``error [code]: message`` on one line (newlines in the message are flattened)."""
    message = " ".join(str(err.message).split())
    return f"error [{err.code.value}]: {message}"


def report_error(err: CapevoError) -> int:
    """Print ``err``'s :func:`error_line` on stderr (passwords masked) and return its exit code."""
    click.echo(_redact(error_line(err)), err=True)
    return exit_code_for(err)


class CapevoGroup(click.Group):
    """A click group that turns errors into one stderr line and a mapped exit code.

    Args:
        lazy_subcommands: ``{name: "module:attribute"}`` commands imported only when used,
            so a heavy group (``trace`` pulls numpy) does not slow down every other command.
    """

    def __init__(self, *args: Any, lazy_subcommands: Mapping[str, str] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.lazy_subcommands: dict[str, str] = dict(lazy_subcommands or {})

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *self.lazy_subcommands})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = self.lazy_subcommands.get(cmd_name)
        if target is None:
            return super().get_command(ctx, cmd_name)
        module_name, attr = target.split(":")
        command = getattr(importlib.import_module(module_name), attr)
        if not isinstance(command, click.Command):
            raise TypeError(f"{target} is not a click command")
        return command

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except CapevoError as err:
            ctx.exit(report_error(err))
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except KeyboardInterrupt:
            click.echo("error [interrupted]: interrupted", err=True)
            ctx.exit(EXIT_INTERRUPTED)
        except Exception as exc:
            if os.environ.get("CAPEVO_DEBUG"):
                raise
            message = f"unexpected {type(exc).__name__}: {exc} (set CAPEVO_DEBUG=1 for the traceback)"
            ctx.exit(report_error(CapevoError(message)))


# Passwords seen on this process's command lines; a message quoting its input must not leak one.
_SEEN_PASSWORDS: set[str] = set()


def _redact(text: str) -> str:
    secrets = set(_SEEN_PASSWORDS)
    env_pw = os.environ.get("CAPEVO_PASSWORD")
    if env_pw:
        secrets.add(env_pw)
    for secret in sorted(secrets, key=len, reverse=True):
        text = text.replace(secret, "****")
    return text


# ---------------------------------------------------------------------------------------
# Registry selection
# ---------------------------------------------------------------------------------------

_SOURCE_RANK = {
    ParameterSource.COMMANDLINE: 3,
    ParameterSource.PROMPT: 3,
    ParameterSource.ENVIRONMENT: 2,
    ParameterSource.DEFAULT_MAP: 1,
    ParameterSource.DEFAULT: 0,
}


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class RegistryOptions:
    """Where the registry is and how to talk to it, as the shared options give it.

    ``root`` is set for a local registry, ``connect`` (non-empty) for a remote one; never both.
    """

    root: Path | None
    connect: tuple[str, ...]
    namespace: str = DEFAULT_NAMESPACE
    user: str | None = None
    password: str | None = dataclasses.field(default=None, repr=False)
    timeout: float = DEFAULT_TIMEOUT_S
    as_json: bool = False

    @property
    def where(self) -> str:
        """Human description of the target, for messages (never includes the password)."""
        return f"root {self.root}" if self.root is not None else f"registry at {', '.join(self.connect)}"


def resolve_target(
    *,
    root: str | None,
    root_source: ParameterSource | None,
    connect: tuple[str, ...],
    connect_source: ParameterSource | None,
) -> tuple[Path | None, tuple[str, ...]]:
    """Pick exactly one of root and connect (invariant 2).

    Returns:
        ``(root, ())`` for a local registry or ``(None, connect)`` for a remote one.

    Raises:
        Invalid: both given at the same level (both on the command line, or both in the
            environment), or neither usable.
    """
    connect = tuple(c for c in connect if c.strip())
    if not connect:
        if not root:
            raise Invalid("give --root DIR or --connect ENDPOINT", details={"field": "root"})
        return Path(root), ()
    root_rank = _SOURCE_RANK.get(root_source, 0) if root else -1
    connect_rank = _SOURCE_RANK.get(connect_source, 0)
    if root_rank == connect_rank:
        origin = "on the command line" if connect_rank == 3 else "in the environment (CAPEVO_ROOT, CAPEVO_CONNECT)"
        raise Invalid(f"give exactly one of --root and --connect; both were given {origin}", details={"field": "root"})
    if root_rank > connect_rank:
        return Path(root), ()  # type: ignore[arg-type]
    return None, connect


def open_from_options(opts: RegistryOptions, *, create: bool = False) -> Registry:
    """Open the registry ``opts`` selects.

    Args:
        opts: Parsed shared options.
        create: Allow a local root that does not exist yet (only ``publish`` creates one);
            otherwise a missing root is a :class:`NotFound`, not an empty registry.

    Raises:
        NotFound: the local root does not exist and ``create`` is false.
        Unavailable, Timeout, Forbidden: from the Zenoh client.
    """
    if opts.root is not None:
        if not create and not opts.root.is_dir():
            raise NotFound(
                f"registry root {str(opts.root)!r} does not exist (pass --root DIR, set CAPEVO_ROOT, "
                "or --connect ENDPOINT)",
                details={"field": "root"},
            )
        from capevo.registry.local import LocalRegistry

        return LocalRegistry(opts.root, actor=opts.user)
    from capevo.registry.open import open_registry

    return open_registry(
        connect=list(opts.connect),
        namespace=opts.namespace,
        user=opts.user,
        password=opts.password,
        timeout=opts.timeout,
    )


@contextlib.contextmanager
def registry_session(opts: RegistryOptions, *, create: bool = False) -> Iterator[Registry]:
    """Open the registry for one command and always close it."""
    reg = open_from_options(opts, create=create)
    try:
        yield reg
    finally:
        reg.close()


def remember_password(password: str | None) -> str | None:
    """Record ``password`` so no error line ever prints it; empty means none."""
    if password:
        _SEEN_PASSWORDS.add(password)
    return password or None


LOGIN_OPTIONS = (
    click.option(
        "--namespace",
        default=DEFAULT_NAMESPACE,
        envvar="CAPEVO_NAMESPACE",
        show_default=True,
        help="Zenoh key prefix of the registry (env CAPEVO_NAMESPACE).",
    ),
    click.option(
        "--user",
        envvar="CAPEVO_USER",
        default=None,
        help="Registry user (env CAPEVO_USER); with --root, only the actor recorded in the audit log.",
    ),
    click.option(
        "--password",
        envvar="CAPEVO_PASSWORD",
        default=None,
        show_envvar=False,
        help="Registry password (env CAPEVO_PASSWORD; prefer the env var; never echoed; unused with --root).",
    ),
)
"""``--namespace``, ``--user`` and ``--password``: the same on every command that talks to a registry."""


def login_options(func: F) -> F:
    """Add :data:`LOGIN_OPTIONS` to a command."""
    for deco in reversed(LOGIN_OPTIONS):
        func = deco(func)
    return func


def registry_options(func: F) -> F:
    """Add ``--root/--connect/--namespace/--user/--password/--timeout/--json`` to a command.

    The wrapped function receives one ``opts: RegistryOptions`` keyword instead.
    """

    @functools.wraps(func)
    def wrapper(
        *args: Any,
        root: str | None,
        connect: tuple[str, ...],
        namespace: str,
        user: str | None,
        password: str | None,
        timeout: float,
        as_json: bool,
        **kwargs: Any,
    ) -> Any:
        ctx = click.get_current_context()
        remember_password(password)
        root_path, endpoints = resolve_target(
            root=root,
            root_source=ctx.get_parameter_source("root"),
            connect=connect,
            connect_source=ctx.get_parameter_source("connect"),
        )
        opts = RegistryOptions(
            root=root_path,
            connect=endpoints,
            namespace=namespace,
            user=user or None,
            password=password or None,
            timeout=timeout,
            as_json=as_json,
        )
        return func(*args, opts=opts, **kwargs)

    decorators = [
        click.option(
            "--root",
            type=click.Path(file_okay=False, path_type=str),
            envvar="CAPEVO_ROOT",
            default=DEFAULT_ROOT,
            show_default=True,
            help="Local registry directory (env CAPEVO_ROOT).",
        ),
        click.option(
            "--connect",
            multiple=True,
            metavar="ENDPOINT",
            envvar="CAPEVO_CONNECT",
            help="Zenoh endpoint of a running registry, e.g. tcp/127.0.0.1:7447; repeatable (env CAPEVO_CONNECT).",
        ),
        *LOGIN_OPTIONS,
        registry_timeout_option,
        json_option,
    ]
    out: Any = wrapper
    for deco in reversed(decorators):
        out = deco(out)
    return out  # type: ignore[no-any-return]


json_option = click.option("--json", "as_json", is_flag=True, help="Print JSON instead of tables.")

registry_timeout_option = click.option(
    "--timeout",
    type=click.FloatRange(min=0.01),
    default=DEFAULT_TIMEOUT_S,
    envvar="CAPEVO_TIMEOUT",
    show_default=True,
    help="Seconds to wait for each registry reply (env CAPEVO_TIMEOUT).",
)
"""``--timeout``: how long a command waits for each reply of a registry it talks to."""

identity_option = click.option(
    "--identity",
    "identity_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Agent identity memory (M_id) YAML. [default: the packaged one]",
)
"""``--identity``: the persistent agent's identity memory (:mod:`capevo.agent`)."""

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
"""How every command's log lines look on stderr."""


def log_level_option(*, default: str = "WARNING", help: str = "Log level (logs go to stderr).") -> Callable[[F], F]:
    """``--log-level DEBUG|INFO|WARNING|ERROR`` (any case), ``default`` shown in the help."""
    return click.option(
        "--log-level",
        type=click.Choice(["DEBUG", "INFO", "WARNING", "ERROR"], case_sensitive=False),
        default=default,
        show_default=True,
        help=help,
    )


def _check_phi(ctx: click.Context, param: click.Parameter, value: str) -> str:
    from capevo.runtime.envelope import check_phi_choice

    return check_phi_choice(value)  # Invalid: refused before anything starts or imports robosuite


phi_option = click.option(
    "--phi",
    default="task",
    show_default=True,
    callback=_check_phi,
    help="Safety envelope Φ: 'task' (the paper's Φ plus the task's scene: it brakes before contacts), "
    "'paper' (the paper's Φ alone, to reproduce its table) or a Φ YAML file.",
)
"""``--phi``: which envelope episodes run under (:mod:`capevo.runtime.envelope`)."""


def log_to_stderr(level: str) -> None:
    """Send log records of ``level`` and above to stderr in :data:`LOG_FORMAT`."""
    logging.basicConfig(level=level.upper(), stream=sys.stderr, format=LOG_FORMAT)


# ---------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------


def stdout_console() -> Console:
    """A rich console on the current stdout (which click's test runner may have replaced).

    Off a terminal, lines are not wrapped at 80 columns: tables are read by scripts and logs.
    """
    stream = sys.stdout
    is_tty = hasattr(stream, "isatty") and stream.isatty()
    width = None if is_tty else int(os.environ.get("COLUMNS") or 200)
    # markup=False: values such as predicates contain '[...]', which must print verbatim.
    return Console(file=stream, highlight=False, markup=False, soft_wrap=False, width=width, emoji=False)


def stderr_console() -> Console:
    stream = sys.stderr
    return Console(file=stream, highlight=False, markup=False, stderr=True, emoji=False)


def emit(opts_or_json: RegistryOptions | bool, data: Any, render: Callable[[Console], None]) -> None:
    """Print ``data`` as JSON when asked, otherwise call ``render`` with a stdout console.

    Args:
        opts_or_json: The command's options, or the ``--json`` flag itself.
        data: A JSON-able value (records' ``to_dict()`` output).
        render: Draws the human form.
    """
    as_json = opts_or_json if isinstance(opts_or_json, bool) else opts_or_json.as_json
    if as_json:
        click.echo(json.dumps(data, indent=2, allow_nan=False))
    else:
        render(stdout_console())


def make_table(*columns: str) -> Table:
    """A plain table in the house style (simple heading rule, no outer frame)."""
    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False)
    for col in columns:
        table.add_column(col, overflow="fold")
    return table


def fmt_time(ts: float | None) -> str:
    """UTC wall time to the second, e.g. ``2025-03-01 12:00:07Z``."""
    if ts is None:
        return "-"
    return _dt.datetime.fromtimestamp(ts, tz=_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%SZ")


def fmt_bytes(n: int) -> str:
    """Human size: ``512 B``, ``10.0 MB`` (powers of 1024)."""
    size = float(n)
    for unit in ("B", "KB", "MB", "GB"):
        if size < 1024 or unit == "GB":
            return f"{int(size)} B" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{n} B"  # pragma: no cover - loop always returns


def fmt_opt(value: Any) -> str:
    return "-" if value is None or value == "" else str(value)


@contextlib.contextmanager
def progress(message: str, *, enabled: bool = True) -> Iterator[None]:
    """A spinner on stderr while a long call runs; silent when stderr is not a terminal."""
    console = stderr_console()
    if not enabled or not console.is_terminal:
        yield
        return
    with console.status(message):
        yield


# ---------------------------------------------------------------------------------------
# The main group
# ---------------------------------------------------------------------------------------


@click.group(cls=CapevoGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="capevo", prog_name="capevo")
def main() -> None:
    """capevo: capability evolution for embodied agents.

    Registry commands take --root DIR (local, default $CAPEVO_ROOT or ./capevo-data) or
    --connect ENDPOINT (a running `capevo registry serve`), and --json for JSON output.
    Errors print `error [code]: message` on stderr and exit with the code's number
    (3 invalid, 4 not_found, 5 conflict, 6 illegal_transition, 7 forbidden, 8 corrupt,
    9 timeout, 10 unavailable, 11 too_large, 1 internal, 2 usage).
    """


def _register_commands() -> None:
    # Imported here because the subcommand modules import the helpers above.
    from capevo.cli.ecm import ecm
    from capevo.cli.registry import registry

    main.add_command(ecm)
    main.add_command(registry)
    # The heavy groups (numpy, robosuite, torch) load only when their command runs.
    main.lazy_subcommands.update(
        {
            "trace": "capevo.cli.trace:trace",
            "runtime": "capevo.cli.runtime:runtime",
            "learner": "capevo.cli.learner:learner",
            "evolve": "capevo.cli.evolve:evolve",
            "experiment": "capevo.cli.experiment:experiment",
        }
    )


_register_commands()
