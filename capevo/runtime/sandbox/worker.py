"""The sandbox worker process: loads one skill under lock-down and answers step requests.

Started by :class:`capevo.runtime.sandbox.client.SandboxedSkill` as a fresh interpreter
(``python -I`` with a scrubbed environment, its own session, only fds 0-2). It talks
length-prefixed JSON frames over stdin/stdout (:mod:`capevo.runtime.sandbox.protocol`).

Session:

1. host -> ``{"op": "init", "source", "filename", "params", "validate", "allowed_imports", "limits"}``
2. the worker imports the allowed modules, applies :func:`capevo.runtime.sandbox.limits.lock_down`,
   then validates and runs the source; it replies ``{"ok": true, "layers", "params", "defaults"}``
   or ``{"ok": false, "kind": <error code>, "error": <message>}`` and exits.
3. host -> ``{"op": "step", "obs": <arrays>}``; worker -> ``{"ok": true, "done": bool,
   "action": [shape, flat values] | null}`` or ``{"ok": false, "kind": "exception" |
   "bad_output" | "protocol", "error": <text>}``.
4. ``{"op": "params", "params": {...}}`` replaces θ; ``{"op": "ping"}``; ``{"op": "exit"}``.

Invariants:
1. Nothing the skill raises ends the worker; only the kernel (SIGXCPU, memory) or the host
   (SIGKILL after a timeout) does.
2. The skill never runs before :func:`lock_down` has returned.
3. Replies contain only JSON types.
"""

from __future__ import annotations

import importlib
import os
import sys
import types
from collections.abc import Mapping
from typing import Any, BinaryIO

from capevo.errors import CapevoError, Invalid
from capevo.runtime.sandbox.limits import WorkerLimits, arm_cpu, lock_down
from capevo.runtime.sandbox.namespace import BadOutput, SkillModule, action_array, load_skill_module, merge_params
from capevo.runtime.sandbox.protocol import (
    PeerClosed,
    ProtocolError,
    decode_arrays,
    encode_frame,
    read_frame_blocking,
)
from capevo.runtime.sandbox.validator import ALLOWED_IMPORTS

MAX_ERROR_CHARS = 2000

BOOTSTRAP = (
    "import sys, types\n"
    "root = sys.argv[1]\n"
    # Bare package objects: the worker must not run capevo/__init__ or capevo/runtime/__init__,
    # which may import heavy or file-touching modules.
    "for name, sub in (('capevo', '/capevo'), ('capevo.runtime', '/capevo/runtime')):\n"
    "    m = types.ModuleType(name); m.__path__ = [root + sub]; sys.modules[name] = m\n"
    "from capevo.runtime.sandbox.worker import main\n"
    "main()\n"
)
"""``python -I -c BOOTSTRAP <dir holding the capevo package>`` starts a worker."""


def _send(fd: int, message: Mapping[str, Any]) -> None:
    view = memoryview(encode_frame(message))
    while view:
        n = os.write(fd, view)
        view = view[n:]


def describe_exception(exc: BaseException, filename: str) -> str:
    """``Type: message (line N of filename)`` without touching files (no linecache)."""
    try:
        text = f"{type(exc).__name__}: {exc}"
    except Exception:  # a hostile __str__
        text = type(exc).__name__
    line = None
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == filename:
            line = tb.tb_lineno
        tb = tb.tb_next
    if line is not None:
        text += f" (line {line} of {filename})"
    return text[:MAX_ERROR_CHARS]


def step_reply(skill: SkillModule, params: Mapping[str, float], obs_wire: object, filename: str) -> dict[str, Any]:
    """Run ``done`` then ``act`` on one observation and build the reply."""
    try:
        obs = decode_arrays(obs_wire)
    except ProtocolError as exc:
        return {"ok": False, "kind": "protocol", "error": str(exc)}
    try:
        if skill.done is not None and bool(skill.done(obs, params)):
            return {"ok": True, "done": True, "action": None}
        arr = action_array(skill.act(obs, params))
    except BadOutput as exc:
        return {"ok": False, "kind": "bad_output", "error": str(exc)[:MAX_ERROR_CHARS]}
    except BaseException as exc:  # a skill may raise anything; the worker survives it
        return {"ok": False, "kind": "exception", "error": describe_exception(exc, filename)}
    return {"ok": True, "done": False, "action": [list(arr.shape), arr.ravel().tolist()]}


def serve(init: Mapping[str, Any], inp: BinaryIO, out_fd: int) -> None:
    """Lock down, load the skill from ``init`` and answer requests until exit or EOF."""
    allowed = tuple(init.get("allowed_imports") or sorted(ALLOWED_IMPORTS))
    for module in allowed:
        importlib.import_module(module)
    limits = WorkerLimits.from_dict(init["limits"])
    layers = lock_down(limits)
    filename = str(init.get("filename") or "<skill>")
    try:
        skill = load_skill_module(
            str(init["source"]),
            params_override=init.get("params"),
            filename=filename,
            validate=bool(init.get("validate", True)),
            allowed_imports=allowed,
        )
    except CapevoError as exc:
        _send(out_fd, {"ok": False, "kind": exc.code.value, "error": exc.message, "details": exc.details})
        return
    params = dict(skill.params)
    _send(out_fd, {"ok": True, "layers": layers, "params": params, "defaults": skill.defaults})
    proxy = types.MappingProxyType(params)
    while True:
        msg = read_frame_blocking(inp)
        op = msg.get("op")
        if op == "step":
            arm_cpu(limits.cpu_seconds_per_call)
            _send(out_fd, step_reply(skill, proxy, msg.get("obs"), filename))
        elif op == "params":
            try:
                merged = merge_params(skill.defaults, msg.get("params"))
            except Invalid as exc:
                _send(out_fd, {"ok": False, "kind": exc.code.value, "error": exc.message})
                continue
            params.clear()
            params.update(merged)
            _send(out_fd, {"ok": True, "params": params})
        elif op == "ping":
            _send(out_fd, {"ok": True})
        elif op == "exit":
            return
        else:
            _send(out_fd, {"ok": False, "kind": "protocol", "error": f"unknown op {op!r}"})


def main() -> None:
    """Entry point of the worker process."""
    inp = sys.stdin.buffer
    # Stray prints (ours or a skill's) must not corrupt the protocol on fd 1.
    sys.stdout = sys.stderr
    try:
        init = read_frame_blocking(inp)
        serve(init, inp, 1)
    except (PeerClosed, ProtocolError, BrokenPipeError):
        pass


if __name__ == "__main__":
    main()
