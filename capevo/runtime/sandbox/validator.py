"""Static check of untrusted skill source before any of it runs.

The validator parses the source and walks every node of the AST. It is the first of the
sandbox's layers (see :mod:`capevo.runtime.sandbox`), not the only one: the worker process
also restricts builtins, file descriptors, processes and syscalls, so a construct this walk
misses still cannot read a file or open a socket.

Rules (each rejection names the line, column and construct):

* imports only of :data:`ALLOWED_IMPORTS` (``import numpy as np`` is fine); no relative or
  star imports; imported names follow the attribute rules below;
* none of the names in :data:`FORBIDDEN_NAMES` (``open``, ``exec``, ``eval``, ``compile``,
  ``__import__``, ``globals``, ``setattr`` ...), as a name, a call or a stored value;
* ``getattr``/``hasattr`` only called directly with a string literal that does not start
  with ``_`` as the attribute name;
* no dunder names (``__builtins__``, ``__loader__`` ...) except ``__name__``;
* no attribute whose name starts with ``_`` (``__class__``, ``__subclasses__``,
  ``__globals__``, ``np._core`` ...), is in :data:`FORBIDDEN_ATTRIBUTES` (numpy file I/O,
  pickling, ``ctypes``, ``str.format``, and every name by which a numpy module exposes a
  non-numpy module, such as ``np.ma.core.builtins``), or starts with a prefix in
  :data:`FORBIDDEN_ATTRIBUTE_PREFIXES` (frame, traceback and code object internals);
* no ``class`` statements and no ``async`` constructs.

Invariants:
1. :func:`validate_source` never raises anything but :class:`Invalid` (text that is not
   Python, or too long) or :class:`SandboxViolation` (Python that breaks a rule), for any
   input string.
2. Every :class:`SandboxViolation` message starts with ``line L, col C:`` of the first
   violation, and ``details`` carries ``line``, ``col``, ``construct`` and ``violations``
   (all violations found, at most :data:`MAX_REPORTED`).
3. Source that passes is returned as its parsed :class:`ast.Module`, ready to compile.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from capevo.errors import Invalid, SandboxViolation

MAX_SOURCE_CHARS = 256 * 1024
"""Longest source accepted; skills are small and parse time grows with size."""

MAX_REPORTED = 20

ALLOWED_IMPORTS: frozenset[str] = frozenset({"math", "numpy", "numpy.linalg", "__future__"})
"""Modules untrusted code may import; the worker imports them before it locks itself down."""

FORBIDDEN_NAMES: frozenset[str] = frozenset(
    {
        "open",
        "exec",
        "eval",
        "compile",
        "__import__",
        "globals",
        "locals",
        "vars",
        "getattr",
        "hasattr",
        "setattr",
        "delattr",
        "breakpoint",
        "memoryview",
        "super",
        "classmethod",
        "staticmethod",
        "exit",
        "quit",
    }
)
"""Builtins that read files, run code, or reach interpreter internals.

``getattr`` and ``hasattr`` appear here because only their direct-call form with a safe
literal attribute is allowed (see the module docstring); any other use is rejected. Other
builtins that are merely absent from the sandbox (``type``, ``dir``, ``input`` ...) are not
listed: they are common variable names, and unbound they fail with ``NameError`` at run time.
"""

_GUARDED_GETTERS: frozenset[str] = frozenset({"getattr", "hasattr"})

ALLOWED_DUNDER_NAMES: frozenset[str] = frozenset({"__name__"})
"""``if __name__ == "__main__":`` is common in generated code and harmless."""

FORBIDDEN_ATTRIBUTES: frozenset[str] = frozenset(
    {
        # numpy file and pickle I/O
        "load",
        "loads",
        "save",
        "savez",
        "savez_compressed",
        "savetxt",
        "loadtxt",
        "genfromtxt",
        "fromfile",
        "tofile",
        "fromregex",
        "memmap",
        "dump",
        "dumps",
        "DataSource",
        # numpy corners that reach C memory, the file system or other modules
        "ctypes",
        "ctypeslib",
        "lib",
        "f2py",
        "distutils",
        "testing",
        "info",
        "source",
        "lookfor",
        "show_config",
        "os",
        "sys",
        "compat",  # numpy.compat: open_latin1, npy_load_module (exec from a path), pickle
        # attributes by which numpy's own modules expose other modules (numpy 1.26):
        # np.ma.core.builtins.open, np.ma.core.inspect, np.compat.pickle ... A test walks
        # everything reachable from the allowed modules to keep this list complete.
        "abc",
        "ast",
        "builtins",
        "collections",
        "contextlib",
        "functools",
        "importlib",
        "inspect",
        "io",
        "itertools",
        "numbers",
        "operator",
        "pickle",
        "re",
        "textwrap",
        "types",
        "warnings",
        # str.format can walk attributes, including dunders, from a format string
        "format",
        "format_map",
        "mro",
    }
)

FORBIDDEN_ATTRIBUTE_PREFIXES: tuple[str, ...] = ("_", "gi_", "cr_", "ag_", "f_", "tb_", "co_", "func_")
"""Frame, generator, coroutine, traceback and code internals lead back to the host's globals."""

_FORBIDDEN_NODES: dict[type[ast.AST], str] = {
    ast.ClassDef: "class statement",
    ast.AsyncFunctionDef: "async def",
    ast.Await: "await",
    ast.AsyncFor: "async for",
    ast.AsyncWith: "async with",
}


@dataclass(frozen=True, slots=True, kw_only=True)
class Violation:
    """One rule broken at one place."""

    line: int
    col: int
    construct: str
    reason: str

    def to_dict(self) -> dict[str, object]:
        return {"line": self.line, "col": self.col, "construct": self.construct, "reason": self.reason}

    def __str__(self) -> str:
        return f"line {self.line}, col {self.col}: {self.construct}: {self.reason}"


def parse_source(source: str, *, filename: str = "<skill>") -> ast.Module:
    """Parse ``source`` as a module.

    Raises:
        Invalid: the text is too long, not a string, or not valid Python.
    """
    if not isinstance(source, str):
        raise Invalid(f"{filename}: skill source must be text, got {type(source).__name__}")
    if len(source) > MAX_SOURCE_CHARS:
        raise Invalid(f"{filename}: skill source is {len(source)} characters; the limit is {MAX_SOURCE_CHARS}")
    try:
        return ast.parse(source, filename=filename, mode="exec")
    except SyntaxError as exc:
        where = f"line {exc.lineno}, col {exc.offset}: " if exc.lineno else ""
        raise Invalid(f"{filename}: {where}not valid Python: {exc.msg}", details={"line": exc.lineno}) from None
    except (ValueError, RecursionError, MemoryError, OverflowError) as exc:
        # ValueError: NUL bytes; RecursionError/MemoryError: pathological nesting.
        raise Invalid(f"{filename}: not valid Python: {type(exc).__name__}: {exc}") from None


def find_violations(tree: ast.AST, *, allowed_imports: Iterable[str] = ALLOWED_IMPORTS) -> list[Violation]:
    """Every rule violation in ``tree``, in source order.

    Args:
        tree: A parsed module.
        allowed_imports: Module names that may be imported.

    Returns:
        The violations sorted by (line, col); empty if the tree passes.
    """
    allowed = frozenset(allowed_imports)
    out: list[Violation] = []
    safe_getter_calls: set[int] = set()

    def add(node: ast.AST, construct: str, reason: str) -> None:
        out.append(
            Violation(
                line=getattr(node, "lineno", 0),
                col=getattr(node, "col_offset", 0),
                construct=construct,
                reason=reason,
            )
        )

    # ast.walk is breadth-first and iterative, so deep nesting cannot overflow the stack here.
    nodes = list(ast.walk(tree))
    for node in nodes:
        # Mark getattr(x, "name") calls first so the Name visit below can tell them apart.
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _GUARDED_GETTERS:
            if _safe_getter_call(node):
                safe_getter_calls.add(id(node.func))
            else:
                add(
                    node,
                    f"{node.func.id}(...)",
                    "only allowed as a direct call with a string literal attribute that does not start with '_'",
                )
                safe_getter_calls.add(id(node.func))  # reported once, as the call

    for node in nodes:
        kind = _FORBIDDEN_NODES.get(type(node))
        if kind is not None:
            add(node, kind, "not allowed in skills")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name not in allowed:
                    add(node, f"import {alias.name}", _import_reason(allowed))
                if alias.asname is not None:
                    _check_binding(alias.asname, node, add)
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                add(node, f"from {'.' * node.level}{module} import ...", "relative imports are not allowed")
            elif module not in allowed:
                add(node, f"from {module} import ...", _import_reason(allowed))
            for alias in node.names:
                if alias.name == "*":
                    add(node, f"from {module} import *", "star imports are not allowed")
                else:
                    reason = attribute_reason(alias.name)
                    if reason is not None and module != "__future__":
                        add(node, f"from {module} import {alias.name}", reason)
                    if alias.asname is not None:
                        _check_binding(alias.asname, node, add)
        elif isinstance(node, ast.Name):
            if id(node) in safe_getter_calls:
                continue
            reason = _name_reason(node.id)
            if reason is not None:
                add(node, f"name {node.id!r}", reason)
        elif isinstance(node, ast.Attribute):
            reason = attribute_reason(node.attr)
            if reason is not None:
                add(node, f"attribute .{node.attr}", reason)
        elif isinstance(node, (ast.FunctionDef, ast.Lambda)):
            if isinstance(node, ast.FunctionDef):
                _check_binding(node.name, node, add)
            args = node.args
            for a in (*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg):
                if a is not None:
                    _check_binding(a.arg, a, add)
        elif isinstance(node, ast.ExceptHandler) and node.name is not None:
            _check_binding(node.name, node, add)
        elif isinstance(node, (ast.Global, ast.Nonlocal)):
            for name in node.names:
                _check_binding(name, node, add)
        elif isinstance(node, ast.keyword) and node.arg is not None and node.arg.startswith("__"):
            add(node, f"keyword {node.arg}=", "dunder keyword arguments are not allowed")
        elif isinstance(node, (ast.MatchAs, ast.MatchStar)) and node.name is not None:
            _check_binding(node.name, node, add)
        elif isinstance(node, ast.MatchClass):
            add(node, "class pattern", "class patterns are not allowed in skills")
        elif isinstance(node, ast.MatchMapping) and node.rest is not None:
            _check_binding(node.rest, node, add)
    out.sort(key=lambda v: (v.line, v.col))
    return out


def validate_source(
    source: str, *, filename: str = "<skill>", allowed_imports: Iterable[str] = ALLOWED_IMPORTS
) -> ast.Module:
    """Parse and check untrusted skill source.

    Args:
        source: Python source text.
        filename: Name used in messages and in the compiled code object.
        allowed_imports: Module names that may be imported.

    Returns:
        The parsed module.

    Raises:
        Invalid: the text is too long or not valid Python.
        SandboxViolation: the source breaks a rule; the message names the first violation.
    """
    tree = parse_source(source, filename=filename)
    violations = find_violations(tree, allowed_imports=allowed_imports)
    if violations:
        first = violations[0]
        more = f" (and {len(violations) - 1} more)" if len(violations) > 1 else ""
        raise SandboxViolation(
            f"{first}{more}",
            details={
                "filename": filename,
                "line": first.line,
                "col": first.col,
                "construct": first.construct,
                "violations": [v.to_dict() for v in violations[:MAX_REPORTED]],
            },
        )
    return tree


def _safe_getter_call(node: ast.Call) -> bool:
    if len(node.args) not in (2, 3) or node.keywords:
        return False
    attr = node.args[1]
    return isinstance(attr, ast.Constant) and isinstance(attr.value, str) and attribute_reason(attr.value) is None


def _import_reason(allowed: frozenset[str]) -> str:
    return f"only these modules may be imported: {', '.join(sorted(allowed))}"


def _name_reason(name: str) -> str | None:
    if name in FORBIDDEN_NAMES:
        return "this builtin is not available to skills"
    if name.startswith("__") and name.endswith("__") and name not in ALLOWED_DUNDER_NAMES:
        return "dunder names are not allowed"
    return None


def attribute_reason(attr: str) -> str | None:
    """Why skills may not use attribute ``attr``, or None if they may."""
    if attr.startswith("__"):
        return "dunder attributes are not allowed"
    if attr.startswith(FORBIDDEN_ATTRIBUTE_PREFIXES):
        return "private and interpreter-internal attributes are not allowed"
    if attr in FORBIDDEN_ATTRIBUTES:
        return "this attribute reaches files, pickles, C memory or interpreter internals"
    return None


def _check_binding(name: str, node: ast.AST, add: Callable[[ast.AST, str, str], None]) -> None:
    reason = _name_reason(name)
    if reason is not None:
        add(node, f"binding {name!r}", reason)
