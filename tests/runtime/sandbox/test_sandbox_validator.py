"""The AST validator: what it accepts, what it rejects and how it says so."""

from __future__ import annotations

import ast
import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import ErrorCode, Invalid, SandboxViolation
from capevo.runtime.sandbox.validator import MAX_REPORTED, MAX_SOURCE_CHARS, find_violations, validate_source

GOOD = '''
"""Reach above the cube."""
from __future__ import annotations

import math
import numpy as np
import numpy.linalg
from numpy import clip as np_clip

PARAMS = {"gain": 8.0, "hover": 0.1}


def _target(obs, params):
    return obs["cube_pos"] + np.array([0.0, 0.0, params["hover"]])


def act(obs, params):
    delta = (_target(obs, params) - obs["eef_pos"]) * params["gain"]
    move = [float(v) for v in np_clip(delta, -1.0, 1.0)]
    if getattr(np, "pi", 3.14) > 3 and hasattr(math, "tau"):
        move = list(move)
    try:
        dir = numpy.linalg.norm(delta)
    except (ValueError, ZeroDivisionError) as exc:
        dir = 0.0
    match len(move):
        case 3:
            pass
        case _:
            pass
    f"{dir:.3f}"
    return [*move, 0.0, 0.0, 0.0, -1.0 if dir > 0 else 1.0]


def done(obs, params):
    return bool(math.dist(obs["cube_pos"], obs["eef_pos"]) < 0.01)


if __name__ == "__main__":
    pass
'''


def test_a_realistic_skill_passes_and_comes_back_parsed() -> None:
    tree = validate_source(GOOD)
    assert isinstance(tree, ast.Module)
    assert find_violations(tree) == []


REJECTED = [
    ("import os", 1, "import os"),
    ("import sys as s", 1, "import sys"),
    ("import subprocess", 1, "import subprocess"),
    ("import socket", 1, "import socket"),
    ("import io", 1, "import io"),
    ("import pathlib", 1, "import pathlib"),
    ("from os import path", 1, "from os import ..."),
    ("from . import x", 1, "from . import ..."),
    ("from math import *", 1, "from math import *"),
    ("from numpy import load", 1, "from numpy import load"),
    ("x = 1\nopen('/etc/passwd')", 2, "name 'open'"),
    ("exec('1')", 1, "name 'exec'"),
    ("eval('1')", 1, "name 'eval'"),
    ("compile('1', 'f', 'exec')", 1, "name 'compile'"),
    ("__import__('os')", 1, "name '__import__'"),
    ("globals()", 1, "name 'globals'"),
    ("f = getattr", 1, "name 'getattr'"),
    ("getattr(1, '__class__')", 1, "getattr(...)"),
    ("getattr(1, name)", 1, "getattr(...)"),
    ("hasattr(1, '_x')", 1, "hasattr(...)"),
    ("setattr(1, 'a', 2)", 1, "name 'setattr'"),
    ("().__class__", 1, "attribute .__class__"),
    ("().__class__.__base__.__subclasses__()", 1, "attribute .__"),
    ("def f(): pass\nf.__globals__", 2, "attribute .__globals__"),
    ("x = __builtins__", 1, "name '__builtins__'"),
    ("import numpy as np\nnp._core", 2, "attribute ._core"),
    ("import numpy as np\nnp.load('x')", 2, "attribute .load"),
    ("import numpy as np\nnp.zeros(3).tofile('x')", 2, "attribute .tofile"),
    ("import numpy as np\nnp.ctypeslib", 2, "attribute .ctypeslib"),
    ("'{0.__class__}'.format(1)", 1, "attribute .format"),
    ("def g():\n    yield 1\ng().gi_frame", 3, "attribute .gi_frame"),
    ("try:\n    pass\nexcept Exception as e:\n    e.tb_frame", 4, "attribute .tb_frame"),
    ("class A:\n    pass", 1, "class statement"),
    ("async def f():\n    pass", 1, "async def"),
    ("def __init__(self): pass", 1, "binding '__init__'"),
    ("def f(__builtins__): pass", 1, "binding '__builtins__'"),
    ("match 1:\n    case int(x):\n        pass", 2, "class pattern"),
]


@pytest.mark.parametrize(("source", "line", "construct"), REJECTED)
def test_forbidden_constructs_are_rejected_naming_line_and_construct(source: str, line: int, construct: str) -> None:
    with pytest.raises(SandboxViolation) as info:
        validate_source(source)
    err = info.value
    assert err.code is ErrorCode.SANDBOX_VIOLATION
    assert err.message.startswith(f"line {line}, col ")
    assert construct in err.message
    assert err.details["line"] == line
    assert construct in err.details["construct"] or construct in err.message
    assert err.details["violations"][0]["line"] == line


def test_every_violation_is_listed_in_details_and_counted_in_the_message() -> None:
    with pytest.raises(SandboxViolation) as info:
        validate_source("import os\nimport sys\nopen('x')\n")
    err = info.value
    assert [v["line"] for v in err.details["violations"]] == [1, 2, 3]
    assert "(and 2 more)" in err.message


def test_reported_violations_are_capped() -> None:
    source = "\n".join(f"x{i} = ().__class__" for i in range(MAX_REPORTED + 5))
    with pytest.raises(SandboxViolation) as info:
        validate_source(source)
    assert len(info.value.details["violations"]) == MAX_REPORTED
    assert f"(and {MAX_REPORTED + 4} more)" in info.value.message


def test_allowed_imports_are_configurable() -> None:
    validate_source("import json", allowed_imports={"json"})
    with pytest.raises(SandboxViolation, match="only these modules may be imported: json"):
        validate_source("import math", allowed_imports={"json"})


def test_syntax_errors_are_invalid_with_the_line() -> None:
    with pytest.raises(Invalid) as info:
        validate_source("x = 1\ndef f(:\n")
    assert info.value.code is ErrorCode.INVALID
    assert "line 2" in info.value.message
    assert "not valid Python" in info.value.message


@pytest.mark.parametrize(
    ("source", "fragment"),
    [("a\x00b", "not valid Python"), ("x" * (MAX_SOURCE_CHARS + 1), "limit"), ("(" * 300 + ")" * 300, "Python")],
)
def test_pathological_text_is_invalid(source: str, fragment: str) -> None:
    with pytest.raises(Invalid, match=fragment):
        validate_source(source)


def test_non_text_source_is_invalid() -> None:
    with pytest.raises(Invalid, match="must be text"):
        validate_source(b"x = 1")  # type: ignore[arg-type]


def _never_crashes(source: str) -> None:
    with contextlib.suppress(SandboxViolation, Invalid):
        validate_source(source)


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=400))
def test_arbitrary_text_never_crashes_the_validator(source: str) -> None:
    _never_crashes(source)


_TOKENS = [
    "import", "from", "os", "numpy", "np", "as", "def", "f", "(", ")", ":", "\n", "    ", "return", "x",
    "=", ".", "__class__", "__subclasses__", "open", "getattr", "'__globals__'", ",", "[", "]", "lambda",
    "yield", "class", "async", "await", "for", "in", "if", "else", "try", "except", "*", "**", "1", "'s'",
    "match", "case", "global", "nonlocal", "with", "del", "@", "not", "is", "None", "f'{x}'", "__name__",
]  # fmt: skip


@settings(max_examples=400, deadline=None)
@given(st.lists(st.sampled_from(_TOKENS), max_size=40).map(" ".join))
def test_python_like_token_soup_never_crashes_the_validator(source: str) -> None:
    _never_crashes(source)


@settings(max_examples=200, deadline=None)
@given(
    name=st.sampled_from(["open", "exec", "eval", "compile", "globals", "setattr", "breakpoint"]),
    indent=st.integers(min_value=0, max_value=3),
)
def test_forbidden_builtins_are_found_at_any_depth(name: str, indent: int) -> None:
    lines = []
    for level in range(indent):
        lines.append("    " * level + f"def f{level}():")
    lines.append("    " * indent + f"return {name}")
    with pytest.raises(SandboxViolation) as info:
        validate_source("\n".join(lines))
    assert info.value.details["line"] == indent + 1
    assert name in info.value.message


def _reachable_foreign_modules() -> list[str]:
    """Paths from the allowed modules to any module outside numpy/math, following only
    attribute names the validator admits (through modules and classes)."""
    import collections
    import importlib
    import types

    from capevo.runtime.sandbox.validator import ALLOWED_IMPORTS, attribute_reason

    allowed_top = {name.partition(".")[0] for name in ALLOWED_IMPORTS} - {"__future__"}
    queue = collections.deque(
        (importlib.import_module(name), name) for name in sorted(ALLOWED_IMPORTS) if name != "__future__"
    )
    seen: set[int] = set()
    found: list[str] = []
    while queue:
        obj, path = queue.popleft()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        for attr in list(vars(obj)):
            if attribute_reason(attr) is not None:
                continue
            try:
                value = getattr(obj, attr)
            except Exception:
                continue
            if isinstance(value, types.ModuleType):
                if value.__name__.partition(".")[0] not in allowed_top:
                    found.append(f"{path}.{attr} -> {value.__name__}")
                else:
                    queue.append((value, f"{path}.{attr}"))
            elif isinstance(value, type) and path.count(".") < 6:
                queue.append((value, f"{path}.{attr}"))
    return found


def test_no_attribute_chain_from_allowed_modules_reaches_another_module() -> None:
    # e.g. np.ma.core.builtins.open or np.compat.pickle would bypass the import allow-list
    assert _reachable_foreign_modules() == []
    with pytest.raises(SandboxViolation, match=r"attribute \.builtins"):
        validate_source("import numpy as np\nnp.ma.core.builtins.open('/etc/passwd')\n")
