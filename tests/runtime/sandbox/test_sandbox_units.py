"""In-process pieces of the sandbox: restricted namespace, wire protocol, seccomp program."""

from __future__ import annotations

import contextlib
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from capevo.errors import ErrorCode, Invalid, SandboxViolation
from capevo.runtime.sandbox import limits
from capevo.runtime.sandbox.namespace import (
    SAFE_BUILTIN_NAMES,
    BadOutput,
    action_array,
    load_skill_module,
    merge_params,
    safe_builtins,
)
from capevo.runtime.sandbox.protocol import (
    HEADER,
    FrameReader,
    PeerClosed,
    ProtocolError,
    decode_arrays,
    decode_frame_body,
    encode_arrays,
    encode_frame,
)

SKILL = """
import numpy as np
PARAMS = {"gain": 2.0, "offset": -1}
def act(obs, params):
    return obs["x"] * params["gain"] + params["offset"]
def done(obs, params):
    return obs["x"][0] > 10
"""


# --- namespace ---------------------------------------------------------------------------


def test_load_skill_module_exposes_act_done_and_merged_params() -> None:
    mod = load_skill_module(SKILL, params_override={"gain": 3})
    assert mod.defaults == {"gain": 2.0, "offset": -1.0}
    assert mod.params == {"gain": 3.0, "offset": -1.0}
    assert mod.act({"x": np.array([1.0, 2.0])}, mod.params).tolist() == [2.0, 5.0]
    assert mod.done is not None and not mod.done({"x": np.array([1.0])}, mod.params)


def test_skills_see_only_the_safe_builtins() -> None:
    table = safe_builtins()
    assert set(table) == {*SAFE_BUILTIN_NAMES, "print", "__import__"}
    for name in ("open", "exec", "eval", "compile", "getattr", "globals", "type", "object"):
        assert name not in table
    # With validation skipped, a name the validator would reject is simply not there.
    mod = load_skill_module("def act(obs, params):\n    return open('/etc/passwd')\n", validate=False)
    with pytest.raises(NameError, match="open"):
        mod.act({}, {})


def test_restricted_import_admits_only_the_allow_list() -> None:
    mod = load_skill_module("def act(obs, params):\n    import os\n    return os\n", validate=False)
    with pytest.raises(ImportError, match="'os' is not allowed"):
        mod.act({}, {})
    mod = load_skill_module("def act(obs, params):\n    from numpy import load\n    return load\n", validate=False)
    with pytest.raises(ImportError, match="'load'"):
        mod.act({}, {})
    # json is loaded in this process, but it is not under an allowed package
    mod = load_skill_module("def act(obs, params):\n    import json\n    return json\n", validate=False)
    with pytest.raises(ImportError, match="'json' is not allowed"):
        mod.act({}, {})


def test_numpy_internals_can_import_loaded_submodules() -> None:
    # ndarray.__repr__ imports numpy.core.arrayprint through the skill's __import__.
    mod = load_skill_module("import numpy as np\ndef act(obs, params):\n    return repr(np.arange(3))\n")
    assert mod.act({}, {}) == "array([0, 1, 2])"


def test_print_is_a_no_op() -> None:
    mod = load_skill_module("def act(obs, params):\n    print('hi')\n    return [1.0]\n")
    assert mod.act({}, {}) == [1.0]


@pytest.mark.parametrize(
    ("source", "fragment"),
    [
        ("x = 1", "must define a function act"),
        ("act = 3", "must define a function act"),
        ("def act(o, p): pass\ndone = 1", "done must be a function"),
        ("def act(o, p): pass\nPARAMS = [1]", "must be a dict"),
        ("def act(o, p): pass\nPARAMS = {'a': 'x'}", "must be a number"),
        ("def act(o, p): pass\nPARAMS = {'a': True}", "must be a number"),
        ("def act(o, p): pass\nPARAMS = {'a': float('nan')}", "must be finite"),
        ("def act(o, p): pass\nraise ValueError('boom')", "top-level code raised ValueError: boom"),
    ],
)
def test_contract_violations_are_invalid(source: str, fragment: str) -> None:
    with pytest.raises(Invalid) as info:
        load_skill_module(source)
    assert info.value.code is ErrorCode.INVALID
    assert fragment in info.value.message


def test_validation_runs_before_any_code() -> None:
    with pytest.raises(SandboxViolation):
        load_skill_module("import os\nos.remove('/tmp/x')\ndef act(o, p): pass\n")


def test_params_override_must_name_declared_keys() -> None:
    with pytest.raises(Invalid, match=r"unknown parameter\(s\) \['nope'\]"):
        merge_params({"gain": 1.0}, {"nope": 2})
    with pytest.raises(Invalid, match="must be finite"):
        merge_params({"gain": 1.0}, {"gain": math.inf})


@pytest.mark.parametrize("bad", ["abc", b"x", None, {"a": 1}, [[1, 2], [3]], [object()], np.zeros(5000)])
def test_action_array_rejects_non_actions(bad: object) -> None:
    with pytest.raises(BadOutput):
        action_array(bad)


def test_action_array_keeps_shape() -> None:
    assert action_array([[1, 2]]).shape == (1, 2)
    assert action_array((1, 2.5)).dtype == np.float64


# --- protocol ----------------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(
    arrays=st.dictionaries(
        st.text(min_size=1, max_size=8),
        hnp.arrays(
            dtype=st.sampled_from([np.float32, np.float64, np.int32, np.int64, np.bool_, np.uint8]),
            shape=hnp.array_shapes(min_dims=0, max_dims=3, max_side=4),
        ),
        max_size=4,
    )
)
def test_arrays_round_trip_bit_for_bit(arrays: dict[str, np.ndarray]) -> None:
    frame = encode_frame({"obs": encode_arrays(arrays)})
    back = decode_arrays(decode_frame_body(frame[HEADER.size :])["obs"])
    assert set(back) == set(arrays)
    for key, arr in arrays.items():
        assert back[key].dtype == arr.dtype and back[key].shape == arr.shape
        assert back[key].tobytes() == arr.tobytes(order="C")
        assert not back[key].flags.writeable


@settings(max_examples=200, deadline=None)
@given(
    st.recursive(
        st.none() | st.integers() | st.text() | st.floats(), lambda c: st.lists(c) | st.dictionaries(st.text(), c)
    )
)
def test_decode_arrays_raises_only_protocol_error(wire: object) -> None:
    with contextlib.suppress(ProtocolError):
        decode_arrays({"k": wire})


@pytest.mark.parametrize("body", [b"not json", b"[1, 2]", b"\xff\xfe"])
def test_bad_frame_bodies_are_protocol_errors(body: bytes) -> None:
    with pytest.raises(ProtocolError):
        decode_frame_body(body)


def test_frame_reader_handles_split_frames_oversize_and_eof() -> None:
    r, w = os.pipe()
    os.set_blocking(r, False)
    reader = FrameReader(r, max_frame=64)
    frame = encode_frame({"a": 1})
    os.write(w, frame[:3])
    with pytest.raises(TimeoutError):
        reader.read(0.0)
    os.write(w, frame[3:] + encode_frame({"b": 2}))
    import time

    assert reader.read(time.monotonic() + 1) == {"a": 1}
    assert reader.read(time.monotonic() + 1) == {"b": 2}
    os.write(w, HEADER.pack(65))
    with pytest.raises(ProtocolError, match="exceeds the limit of 64"):
        reader.read(time.monotonic() + 1)
    os.close(w)
    reader2 = FrameReader(r)
    with pytest.raises(PeerClosed):
        reader2.read(time.monotonic() + 1)
    os.close(r)


# --- seccomp program ---------------------------------------------------------------------


@pytest.mark.parametrize("machine", ["x86_64", "aarch64"])
def test_seccomp_program_is_well_formed(machine: str) -> None:
    prog = limits.build_filter(machine)
    assert len(prog) < 256
    for pc, (code, jt, jf, _k) in enumerate(prog):
        if code == 0x15:  # every jump lands inside the program, forwards
            assert pc + 1 + jt < len(prog) and pc + 1 + jf < len(prog)
    # first checks the ABI, kills on mismatch; falls through to a denial, never to allow
    assert prog[0] == (0x20, 0, 0, 4)
    assert prog[-1] == (0x06, 0, 0, 0x80000000)
    rets = {k for code, _, _, k in prog if code == 0x06}
    assert rets == {0x7FFF0000, 0x00050000 | 1, 0x80000000}


def test_unknown_architecture_has_no_filter() -> None:
    with pytest.raises(ValueError, match="no seccomp syscall table"):
        limits.build_filter("sparc")


def test_worker_limits_round_trip() -> None:
    wl = limits.WorkerLimits(cpu_seconds_per_call=3, cpu_seconds_total=9, memory_bytes=5, seccomp=False)
    assert limits.WorkerLimits.from_dict(wl.to_dict()) == wl


def _run_bpf(prog: list[tuple[int, int, int, int]], data: bytes) -> int:
    """A tiny classic-BPF interpreter for the three opcodes the filter uses."""
    import struct

    acc, pc = 0, 0
    while True:
        code, jt, jf, k = prog[pc]
        if code == 0x20:
            (acc,) = struct.unpack_from("<I", data, k)
            pc += 1
        elif code == 0x15:
            pc += 1 + (jt if acc == k else jf)
        elif code == 0x06:
            return k
        else:  # pragma: no cover - the builder emits nothing else
            raise AssertionError(code)


def _seccomp_data(nr: int, arch: int = 0xC000003E, args: tuple[int, ...] = ()) -> bytes:
    import struct

    padded = (*args, *([0] * (6 - len(args))))
    return struct.pack("<iIQ6Q", nr, arch, 0, *padded)


@pytest.mark.parametrize(
    ("nr", "args", "verdict"),
    [
        (0, (), "allow"),  # read
        (1, (), "allow"),  # write
        (9, (), "allow"),  # mmap
        (2, (), "deny"),  # open
        (257, (), "deny"),  # openat
        (41, (), "deny"),  # socket
        (42, (), "deny"),  # connect
        (59, (), "deny"),  # execve
        (57, (), "deny"),  # fork
        (56, (), "deny"),  # clone
        (62, (), "deny"),  # kill
        (87, (), "deny"),  # unlink
        (101, (), "deny"),  # ptrace
        (302, (0, 0), "allow"),  # prlimit64(self, RLIMIT_CPU)
        (302, (0, 7), "deny"),  # prlimit64(self, RLIMIT_NOFILE)
        (302, (1234, 0), "deny"),  # prlimit64(other pid, ...)
        (160, (0,), "allow"),  # setrlimit(RLIMIT_CPU)
        (160, (7,), "deny"),  # setrlimit(RLIMIT_NOFILE)
        (0x40000000 | 2, (), "deny"),  # x32 ABI open
    ],
)
def test_seccomp_program_verdicts(nr: int, args: tuple[int, ...], verdict: str) -> None:
    expected = {"allow": 0x7FFF0000, "deny": 0x00050001}[verdict]
    assert _run_bpf(limits.build_filter("x86_64"), _seccomp_data(nr, args=args)) == expected


def test_seccomp_program_kills_on_a_foreign_abi() -> None:
    i386 = 0x40000003
    assert _run_bpf(limits.build_filter("x86_64"), _seccomp_data(0, arch=i386)) == 0x80000000
