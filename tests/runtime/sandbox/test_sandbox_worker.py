"""Real sandbox worker processes: results, limits, and attacks that must fail.

The adversarial tests use the sandbox's test hook ``_unsafe_skip_validation`` so that a
payload the validator would reject reaches the worker. The payload escapes the restricted
builtins the classic way (``().__class__.__base__.__subclasses__()`` -> a function's
``__globals__``) and then tries to read files, list directories, open sockets, fork,
raise its own limits, delete files and signal the host. Each attack is first run
in-process without the sandbox to prove it works there, so a passing sandbox test means
the sandbox stopped it.
"""

from __future__ import annotations

import os
import re
import socket
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from capevo.errors import ErrorCode, Invalid, SandboxViolation, Timeout
from capevo.runtime.ecm.code import CodeSkill
from capevo.runtime.sandbox import BadOutput, SandboxConfig, SandboxedSkill, SkillRaised, WorkerDied, WorkerLimits

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="the sandbox worker needs Linux rlimits")

SKILL = """
import numpy as np
PARAMS = {"gain": 2.0}
def act(obs, params):
    if obs["x"][0] < 0:
        raise ValueError("negative input")
    return obs["x"] * params["gain"]
def done(obs, params):
    return bool(obs["x"][0] > 100)
"""

ATTACKS = """
PARAMS = {"port": 0.0, "pid": 0.0}

def _escape():
    found = {}
    for c in ().__class__.__base__.__subclasses__():
        try:
            g = c.__init__.__globals__
        except Exception:
            continue
        if "listdir" in g and "fork" in g and "getpid" in g:
            found["os"] = g
        b = g.get("__builtins__")
        if b is not None and "builtins" not in found:
            found["builtins"] = b if isinstance(b, dict) else b.__dict__
    return found

ESC = _escape()
B = ESC["builtins"]
OS = ESC["os"]


def _read_passwd(params):
    return B["open"]("/etc/passwd").read()[:20]

def _listdir(params):
    return ",".join(OS["listdir"]("/")[:3])

def _socket(params):
    sock = B["__import__"]("socket")
    s = sock.socket(sock.AF_INET, sock.SOCK_STREAM)
    s.connect(("127.0.0.1", int(params["port"])))
    return "connected"

def _libc_socket(params):
    ctypes = OS["sys"].modules["ctypes"]
    libc = ctypes.CDLL(None, use_errno=True)
    fd = libc.socket(2, 1, 0)
    if fd < 0:
        raise B["OSError"](ctypes.get_errno(), "libc socket failed")
    return "socket fd %d" % fd

def _libc_open(params):
    ctypes = OS["sys"].modules["ctypes"]
    libc = ctypes.CDLL(None, use_errno=True)
    fd = libc.open(b"/etc/passwd", 0)
    if fd < 0:
        raise B["OSError"](ctypes.get_errno(), "libc open failed")
    return "opened fd %d" % fd

def _close_then_open(params):
    OS["close"](2)
    return B["open"]("/etc/passwd").read()[:20]

def _fork(params):
    pid = OS["fork"]()
    if pid == 0:
        OS["_exit"](0)
    return "forked %d" % pid

def _raise_nofile(params):
    resource = OS["sys"].modules["resource"]
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))
    return B["open"]("/etc/passwd").read()[:20]

def _unlink(params):
    OS["unlink"]("/tmp/capevo-sandbox-canary-%d" % int(params["pid"]))
    return "unlinked"

def _kill_host(params):
    OS["kill"](int(params["pid"]), 0)
    return "signalled host"

def _garbage(params):
    OS["write"](1, b"\\xff\\xff\\xff\\xffgarbage")
    return "wrote garbage"

ATTACKS = [_read_passwd, _listdir, _socket, _libc_socket, _libc_open, _close_then_open,
           _fork, _raise_nofile, _unlink, _kill_host, _garbage]

def act(obs, params):
    attack = ATTACKS[int(obs["attack"][0])]
    try:
        result = attack(params)
    except Exception as exc:
        raise RuntimeError("BLOCKED " + repr(exc))
    raise RuntimeError("LEAK " + repr(result))
"""

NAMES = [
    "read_passwd",
    "listdir",
    "socket",
    "libc_socket",
    "libc_open",
    "close_then_open",
    "fork",
    "raise_nofile",
    "unlink",
    "kill_host",
    "garbage",
]
FILE_AND_NET = ["read_passwd", "listdir", "socket", "libc_socket", "libc_open", "close_then_open"]


def _obs(name: str) -> dict[str, np.ndarray]:
    return {"attack": np.array([NAMES.index(name)], dtype=np.float32)}


@pytest.fixture
def listener() -> socket.socket:
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    srv.settimeout(0.2)
    yield srv
    srv.close()


@pytest.fixture
def canary() -> Path:
    path = Path(f"/tmp/capevo-sandbox-canary-{os.getpid()}")
    path.write_text("still here")
    yield path
    path.unlink(missing_ok=True)


def _attack_params(listener: socket.socket) -> dict[str, float]:
    return {"port": float(listener.getsockname()[1]), "pid": float(os.getpid())}


def _no_connection(listener: socket.socket) -> bool:
    try:
        conn, _ = listener.accept()
    except TimeoutError:
        return True
    conn.close()
    return False


@pytest.mark.parametrize("name", ["read_passwd", "listdir", "socket", "libc_open", "unlink"])
def test_the_payload_works_without_the_sandbox(name: str, listener: socket.socket, canary: Path) -> None:
    skill = CodeSkill(ATTACKS, _attack_params(listener), _unsafe_skip_validation=True)
    with pytest.raises(RuntimeError, match="LEAK"):
        skill.act(_obs(name))
    if name == "socket":
        assert not _no_connection(listener)
    if name == "unlink":
        assert not canary.exists()


def test_the_validator_rejects_the_payload() -> None:
    with pytest.raises(SandboxViolation) as info:
        SandboxedSkill(ATTACKS)
    assert info.value.code is ErrorCode.SANDBOX_VIOLATION
    assert info.value.message.startswith("line 6, col 13: attribute .__subclasses__: dunder attributes")


@pytest.mark.parametrize("seccomp", [True, False], ids=["seccomp", "rlimits-only"])
def test_unvalidated_code_cannot_read_files_or_open_sockets(
    seccomp: bool, listener: socket.socket, canary: Path
) -> None:
    config = SandboxConfig(limits=WorkerLimits(seccomp=seccomp))
    with SandboxedSkill(ATTACKS, _attack_params(listener), config=config, _unsafe_skip_validation=True) as skill:
        assert skill.layers["seccomp"] is seccomp
        assert skill.layers["nofile"] == 0
        layer = r"BLOCKED (PermissionError\(1,|ModuleNotFoundError)" if seccomp else r"BLOCKED OSError\(24,"
        for name in FILE_AND_NET:
            with pytest.raises(SkillRaised) as info:
                skill.step(_obs(name), timeout_s=5)
            text = str(info.value)
            # The layer that stopped it: the syscall filter (EPERM; the import machinery cannot
            # even list directories) or, without it, RLIMIT_NOFILE 0 (EMFILE).
            assert re.search(layer, text), (name, text)
            assert "root:" not in text
        assert _no_connection(listener)
        assert canary.read_text() == "still here"


@pytest.mark.skipif(not SandboxConfig().limits.seccomp, reason="seccomp disabled")
@pytest.mark.parametrize("name", ["fork", "raise_nofile", "unlink", "kill_host"])
def test_with_seccomp_process_limit_and_filesystem_attacks_fail(
    name: str, listener: socket.socket, canary: Path
) -> None:
    with SandboxedSkill(ATTACKS, _attack_params(listener), _unsafe_skip_validation=True) as skill:
        if not skill.layers["seccomp"]:
            pytest.skip("seccomp unsupported on this architecture")
        with pytest.raises(SkillRaised, match="BLOCKED") as info:
            skill.step(_obs(name), timeout_s=5)
        assert re.search("Operation not permitted|not allowed to raise maximum limit", str(info.value))
    assert canary.read_text() == "still here"


def test_protocol_garbage_kills_and_replaces_the_worker(listener: socket.socket) -> None:
    with SandboxedSkill(ATTACKS, _attack_params(listener), _unsafe_skip_validation=True) as skill:
        first = skill.pid
        with pytest.raises(WorkerDied, match=r"exceeds the limit|not JSON"):
            skill.step(_obs("garbage"), timeout_s=5)
        assert skill.restarts == 1
        with pytest.raises(SkillRaised, match="BLOCKED"):
            skill.step(_obs("read_passwd"), timeout_s=5)
        assert skill.pid != first


# --- ordinary behaviour --------------------------------------------------------------------


def test_sandboxed_skill_matches_in_process_results() -> None:
    local = CodeSkill(SKILL, {"gain": 3.0})
    with SandboxedSkill(SKILL, {"gain": 3.0}) as remote:
        assert remote.params == {"gain": 3.0} and remote.defaults == {"gain": 2.0}
        for x in ([1.0, 2.0, 3.0], [0.5, -0.0, 7.0]):
            obs = {"x": np.array(x, dtype=np.float32)}
            got = remote.step(obs, timeout_s=5)
            want = local.step(obs, timeout_s=5)
            assert not got.done and got.action is not None and want.action is not None
            np.testing.assert_array_equal(got.action, want.action)
        assert remote.step({"x": np.array([101.0, 0, 0], dtype=np.float32)}, timeout_s=5).done
        with pytest.raises(SkillRaised, match=r"ValueError: negative input \(line 6 of <skill>\)"):
            remote.step({"x": np.array([-1.0, 0, 0], dtype=np.float32)}, timeout_s=5)
        # the worker survives a skill exception
        assert remote.step({"x": np.array([1.0, 1, 1], dtype=np.float32)}, timeout_s=5).action is not None
        assert remote.restarts == 0


def test_set_params_changes_theta_without_restart() -> None:
    with SandboxedSkill(SKILL) as skill:
        pid = skill.pid
        assert skill.set_params({"gain": 10.0}) == {"gain": 10.0}
        step = skill.step({"x": np.array([1.0], dtype=np.float32)}, timeout_s=5)
        assert step.action is not None and step.action.tolist() == [10.0]
        assert skill.pid == pid
        with pytest.raises(Invalid, match="unknown parameter"):
            skill.set_params({"nope": 1.0})


def test_bad_outputs_are_reported_not_fatal() -> None:
    source = "def act(obs, params):\n    return 'left'\n"
    with SandboxedSkill(source) as skill:
        with pytest.raises(BadOutput, match="act returned str"):
            skill.step({}, timeout_s=5)
        assert skill.restarts == 0


def test_contract_errors_surface_at_construction() -> None:
    with pytest.raises(Invalid, match="must define a function act"):
        SandboxedSkill("x = 1\n")
    with pytest.raises(Invalid, match="top-level code raised ZeroDivisionError"):
        SandboxedSkill("x = 1 / 0\ndef act(o, p):\n    return [0.0]\n")


HANG = """
def act(obs, params):
    if obs["x"][0] > 0:
        while True:
            pass
    return [0.0]
"""


def test_infinite_loop_times_out_and_the_worker_is_replaced() -> None:
    with SandboxedSkill(HANG) as skill:
        first = skill.pid
        t0 = time.monotonic()
        with pytest.raises(Timeout) as info:
            skill.step({"x": np.array([1.0], dtype=np.float32)}, timeout_s=0.3)
        assert time.monotonic() - t0 < 2.0
        assert info.value.code is ErrorCode.TIMEOUT
        assert skill.restarts == 1
        step = skill.step({"x": np.array([0.0], dtype=np.float32)}, timeout_s=5)
        assert step.action is not None and step.action.tolist() == [0.0]
        assert skill.pid != first
        with pytest.raises(ProcessLookupError):
            os.kill(first, 0)  # the hung worker is gone, not leaked


def test_cpu_limit_kills_a_loop_even_without_a_wall_clock_timeout() -> None:
    config = SandboxConfig(limits=WorkerLimits(cpu_seconds_per_call=1))
    with SandboxedSkill(HANG, config=config) as skill:
        t0 = time.monotonic()
        with pytest.raises(WorkerDied, match="SIGXCPU"):
            skill.step({"x": np.array([1.0], dtype=np.float32)}, timeout_s=60)
        assert time.monotonic() - t0 < 45  # the kernel, not the 60 s wall clock, ended it
        assert skill.restarts == 1


def test_memory_bombs_hit_the_limit_and_the_worker_lives_on() -> None:
    source = """
import numpy as np
def act(obs, params):
    if obs["x"][0] == 1:
        block = np.ones(10 ** 10)
    if obs["x"][0] == 2:
        hoard = []
        while True:
            hoard.append([1.0] * (4 * 1024 * 1024))
    return [1.0]
"""
    with SandboxedSkill(source) as skill:
        pid = skill.pid
        for kind in (1.0, 2.0):
            with pytest.raises(SkillRaised, match="MemoryError"):
                skill.step({"x": np.array([kind], dtype=np.float32)}, timeout_s=10)
        step = skill.step({"x": np.array([0.0], dtype=np.float32)}, timeout_s=5)
        assert step.action is not None and step.action.tolist() == [1.0]
        assert skill.pid == pid and skill.restarts == 0


NUMPY_HEAVY = """
import math
import numpy as np
def act(obs, params):
    a = np.array([1.0, 0.0]) / np.array([0.0, 0.0])
    c = np.linalg.inv(np.eye(3) * 2.0)
    d = repr(np.arange(3)) + str(np.float32(1.5)) + str(np.eye(2)) + f"{np.float64(2.5):.3f}"
    e = np.quantile(c, 0.5) + np.median(c) + np.std(c) + np.polyfit([0, 1, 2], [0, 2, 4], 1)[0]
    try:
        np.ones(10 ** 12)
    except MemoryError as exc:
        d += str(exc)
    try:
        math.sqrt(-1)
    except ValueError as exc:
        d += str(exc)
    return [float(a[0]), float(a[1]), c[0, 0], float(len(d)), float(e)]
"""


def test_numpy_works_the_same_under_lock_down() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = CodeSkill(NUMPY_HEAVY).step({}, timeout_s=5).action
    with SandboxedSkill(NUMPY_HEAVY) as skill:
        got = skill.step({}, timeout_s=5).action
    assert got is not None and want is not None
    np.testing.assert_array_equal(got, want)  # inf and nan included


def test_top_level_code_is_cpu_limited_too() -> None:
    config = SandboxConfig(limits=WorkerLimits(cpu_seconds_per_call=1))
    with pytest.raises(WorkerDied, match="failed to start: worker killed by SIGXCPU"):
        SandboxedSkill("while True:\n    pass\ndef act(o, p):\n    return [0.0]\n", config=config)


def test_a_skill_that_keeps_hanging_is_declared_dead() -> None:
    config = SandboxConfig(max_restarts=1)
    with SandboxedSkill(HANG, config=config) as skill:
        hang = {"x": np.array([1.0], dtype=np.float32)}
        with pytest.raises(Timeout):
            skill.step(hang, timeout_s=0.2)
        with pytest.raises(Timeout):
            skill.step(hang, timeout_s=0.2)
        t0 = time.monotonic()
        with pytest.raises(WorkerDied, match=r"skill is dead: timed out after 0\.2s"):
            skill.step(hang, timeout_s=0.2)
        assert time.monotonic() - t0 < 0.1
        assert skill.pid is None


def test_close_and_garbage_collection_kill_the_worker() -> None:
    skill = SandboxedSkill(SKILL)
    pid = skill.pid
    assert pid is not None
    skill.close()
    skill.close()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    with pytest.raises(WorkerDied, match="closed"):
        skill.step({"x": np.array([1.0], dtype=np.float32)}, timeout_s=1)

    other = SandboxedSkill(SKILL)
    pid2 = other.pid
    assert pid2 is not None
    del other
    import gc

    gc.collect()
    with pytest.raises(ProcessLookupError):
        os.kill(pid2, 0)


def test_worker_runs_in_its_own_session() -> None:
    # Ctrl-C in the host's terminal must not reach the worker (it has no handler for it).
    with SandboxedSkill(SKILL) as skill:
        assert skill.pid is not None
        assert os.getsid(skill.pid) == skill.pid != os.getsid(0)
