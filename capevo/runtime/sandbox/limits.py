"""The kernel-enforced layers a sandbox worker puts on itself before it loads untrusted code.

Called once in the worker, after every module the skill may use is imported and before
the skill's source runs. Nothing here is undone: every hard limit is lowered for good and a
seccomp filter cannot be removed.

Layers, in the order applied:

1. ``RLIMIT_CORE`` 0 (a CPU-limit kill writes no core file).
2. Every file descriptor but 0, 1, 2 (the pipes to the host, stderr to /dev/null) closed,
   then ``RLIMIT_NOFILE`` 0/0: the process can allocate no new descriptor at all, so
   ``open``, ``socket``, ``opendir``, ``pipe``, ``dup`` fail with EMFILE even after
   closing one of its three.
3. ``RLIMIT_NPROC`` 0/0 (no fork or thread for a non-root user), ``RLIMIT_FSIZE`` 0/0.
4. ``RLIMIT_AS``: the address space in use now plus ``memory_bytes``.
5. ``RLIMIT_CPU``: hard limit for the worker's lifetime; the soft limit is re-armed before
   each call (:func:`arm_cpu`) so one call gets about ``cpu_seconds_per_call`` of CPU before
   the kernel sends SIGXCPU, which kills the worker.
6. A seccomp-bpf allow-list (x86_64 and aarch64) with ``no_new_privs``: only read/write on
   existing descriptors, memory management, signals, clocks, getrusage and exit are
   permitted, plus ``prlimit64``/``setrlimit`` of ``RLIMIT_CPU`` on itself. Everything else
   (open, socket, connect, execve, clone, kill, ptrace, unlink, chmod, stat ...) fails
   with EPERM. Root's CAP_SYS_RESOURCE could raise the hard limits of layers 2-4; the
   filter is what stops that when the host runs as root.

Invariants:
1. After :func:`lock_down` returns, the process has no descriptor above 2 and cannot
   create one.
2. :func:`lock_down` reports which layers are active; ``seccomp`` is False only when the
   architecture is unsupported or the caller disabled it.
"""

from __future__ import annotations

import ctypes
import errno
import os
import platform
import resource
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True, slots=True, kw_only=True)
class WorkerLimits:
    """Resource limits of one sandbox worker.

    Args:
        cpu_seconds_per_call: CPU seconds one call may use before the kernel kills the
            worker (whole seconds: the kernel's granularity). The host's wall-clock
            timeout usually fires first; this is the backstop.
        cpu_seconds_total: Hard CPU limit over the worker's lifetime.
        memory_bytes: Address space the skill may add beyond what the interpreter, numpy
            and the worker already map when the limits are applied.
        seccomp: Install the syscall allow-list where the architecture is supported.
    """

    cpu_seconds_per_call: int = 2
    cpu_seconds_total: int = 3600
    memory_bytes: int = 256 * 1024 * 1024
    seccomp: bool = True

    def to_dict(self) -> dict[str, Any]:
        return {
            "cpu_seconds_per_call": self.cpu_seconds_per_call,
            "cpu_seconds_total": self.cpu_seconds_total,
            "memory_bytes": self.memory_bytes,
            "seccomp": self.seccomp,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> WorkerLimits:
        return cls(
            cpu_seconds_per_call=int(d["cpu_seconds_per_call"]),
            cpu_seconds_total=int(d["cpu_seconds_total"]),
            memory_bytes=int(d["memory_bytes"]),
            seccomp=bool(d["seccomp"]),
        )


# --- seccomp -----------------------------------------------------------------------------

_AUDIT_ARCH = {"x86_64": 0xC000003E, "aarch64": 0xC00000B7}

# Syscalls a locked-down worker needs to read a request, compute with numpy and reply.
_ALLOWED_SYSCALLS: dict[str, dict[str, int]] = {
    "x86_64": {
        "read": 0,
        "write": 1,
        "close": 3,
        "fstat": 5,
        "lseek": 8,
        "mmap": 9,
        "mprotect": 10,
        "munmap": 11,
        "brk": 12,
        "rt_sigaction": 13,
        "rt_sigprocmask": 14,
        "rt_sigreturn": 15,
        "readv": 19,
        "writev": 20,
        "sched_yield": 24,
        "mremap": 25,
        "madvise": 28,
        "nanosleep": 35,
        "getpid": 39,
        "exit": 60,
        "gettimeofday": 96,
        "getrusage": 98,
        "sigaltstack": 131,
        "gettid": 186,
        "futex": 202,
        "restart_syscall": 219,
        "clock_gettime": 228,
        "clock_getres": 229,
        "clock_nanosleep": 230,
        "exit_group": 231,
        "getrandom": 318,
        "rseq": 334,
    },
    "aarch64": {
        "read": 63,
        "write": 64,
        "close": 57,
        "fstat": 80,
        "lseek": 62,
        "mmap": 222,
        "mprotect": 226,
        "munmap": 215,
        "brk": 214,
        "rt_sigaction": 134,
        "rt_sigprocmask": 135,
        "rt_sigreturn": 139,
        "readv": 65,
        "writev": 66,
        "sched_yield": 124,
        "mremap": 216,
        "madvise": 233,
        "nanosleep": 101,
        "getpid": 172,
        "exit": 93,
        "gettimeofday": 169,
        "getrusage": 165,
        "sigaltstack": 132,
        "gettid": 178,
        "futex": 98,
        "restart_syscall": 128,
        "clock_gettime": 113,
        "clock_getres": 114,
        "clock_nanosleep": 115,
        "exit_group": 94,
        "getrandom": 278,
        "rseq": 293,
    },
}
_PRLIMIT64 = {"x86_64": 302, "aarch64": 261}
_SETRLIMIT = {"x86_64": 160, "aarch64": 164}

_BPF_LD_W_ABS = 0x20
_BPF_JEQ_K = 0x15
_BPF_RET_K = 0x06
_RET_ALLOW = 0x7FFF0000
_RET_ERRNO = 0x00050000
_RET_KILL_PROCESS = 0x80000000
_PR_SET_NO_NEW_PRIVS = 38
_PR_SET_SECCOMP = 22
_SECCOMP_MODE_FILTER = 2
# struct seccomp_data: int nr; u32 arch; u64 ip; u64 args[6]
_OFF_NR, _OFF_ARCH = 0, 4


def _off_arg_lo(i: int) -> int:
    return 16 + 8 * i  # little-endian: low word first (x86_64 and aarch64 both)


def seccomp_supported() -> bool:
    """Whether this architecture has a syscall table here."""
    return platform.machine() in _ALLOWED_SYSCALLS


def build_filter(machine: str | None = None) -> list[tuple[int, int, int, int]]:
    """The BPF program as ``(code, jt, jf, k)`` instructions.

    Raises:
        ValueError: the architecture is not supported.
    """
    arch = machine or platform.machine()
    if arch not in _ALLOWED_SYSCALLS:
        raise ValueError(f"no seccomp syscall table for {arch}")
    allowed = sorted(_ALLOWED_SYSCALLS[arch].values())
    # Labels are resolved after layout; ("J", nr, label_true) jumps on equality.
    prog: list[tuple[Any, ...]] = [
        ("I", _BPF_LD_W_ABS, 0, 0, _OFF_ARCH),
        ("JF", _BPF_JEQ_K, _AUDIT_ARCH[arch], "kill"),  # wrong ABI -> kill
        ("I", _BPF_LD_W_ABS, 0, 0, _OFF_NR),
    ]
    prog += [("J", _BPF_JEQ_K, nr, "allow") for nr in allowed]
    prog += [
        ("J", _BPF_JEQ_K, _PRLIMIT64[arch], "prlimit"),
        ("J", _BPF_JEQ_K, _SETRLIMIT[arch], "setrlimit"),
        ("I", _BPF_RET_K, 0, 0, _RET_ERRNO | errno.EPERM),
        # prlimit64(pid, resource, new, old): only pid 0 (self) and RLIMIT_CPU.
        ("L", "prlimit"),
        ("I", _BPF_LD_W_ABS, 0, 0, _off_arg_lo(0)),
        ("JF", _BPF_JEQ_K, 0, "deny"),
        ("I", _BPF_LD_W_ABS, 0, 0, _off_arg_lo(0) + 4),
        ("JF", _BPF_JEQ_K, 0, "deny"),
        ("I", _BPF_LD_W_ABS, 0, 0, _off_arg_lo(1)),
        ("JF", _BPF_JEQ_K, resource.RLIMIT_CPU, "deny"),
        ("I", _BPF_RET_K, 0, 0, _RET_ALLOW),
        # setrlimit(resource, rlim): only RLIMIT_CPU.
        ("L", "setrlimit"),
        ("I", _BPF_LD_W_ABS, 0, 0, _off_arg_lo(0)),
        ("JF", _BPF_JEQ_K, resource.RLIMIT_CPU, "deny"),
        ("L", "allow"),
        ("I", _BPF_RET_K, 0, 0, _RET_ALLOW),
        # BPF jumps only forward, so the argument checks share this denial at the end.
        ("L", "deny"),
        ("I", _BPF_RET_K, 0, 0, _RET_ERRNO | errno.EPERM),
        ("L", "kill"),
        ("I", _BPF_RET_K, 0, 0, _RET_KILL_PROCESS),
    ]
    labels: dict[str, int] = {}
    pc = 0
    for ins in prog:
        if ins[0] == "L":
            labels[ins[1]] = pc
        else:
            pc += 1
    out: list[tuple[int, int, int, int]] = []
    for ins in prog:
        if ins[0] == "L":
            continue
        here = len(out)
        if ins[0] == "I":
            out.append((ins[1], ins[2], ins[3], ins[4]))
        elif ins[0] == "J":  # jump to label if equal, else fall through
            out.append((ins[1], _rel(labels[ins[3]], here), 0, ins[2]))
        else:  # "JF": fall through if equal, else jump to label
            out.append((ins[1], 0, _rel(labels[ins[3]], here), ins[2]))
    return out


def _rel(target: int, here: int) -> int:
    off = target - here - 1
    if not 0 <= off <= 255:
        raise ValueError(f"BPF jump offset {off} out of range")
    return off


class _SockFilter(ctypes.Structure):
    _fields_ = (("code", ctypes.c_ushort), ("jt", ctypes.c_ubyte), ("jf", ctypes.c_ubyte), ("k", ctypes.c_uint))


class _SockFprog(ctypes.Structure):
    _fields_ = (("len", ctypes.c_ushort), ("filter", ctypes.POINTER(_SockFilter)))


def install_seccomp() -> None:
    """Install :func:`build_filter` on the calling (single-threaded) process.

    Raises:
        OSError: prctl refused.
    """
    program = build_filter()
    arr = (_SockFilter * len(program))(*(_SockFilter(*ins) for ins in program))
    fprog = _SockFprog(len(program), arr)
    libc = ctypes.CDLL(None, use_errno=True)
    prctl = libc.prctl
    prctl.restype = ctypes.c_int
    ul = ctypes.c_ulong
    if prctl(ctypes.c_int(_PR_SET_NO_NEW_PRIVS), ul(1), ul(0), ul(0), ul(0)) != 0:
        e = ctypes.get_errno()
        raise OSError(e, f"prctl(PR_SET_NO_NEW_PRIVS): {os.strerror(e)}")
    if prctl(ctypes.c_int(_PR_SET_SECCOMP), ul(_SECCOMP_MODE_FILTER), ctypes.byref(fprog), ul(0), ul(0)) != 0:
        e = ctypes.get_errno()
        raise OSError(e, f"prctl(PR_SET_SECCOMP): {os.strerror(e)}")


# --- rlimits -----------------------------------------------------------------------------


def _vm_size_bytes() -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None  # no /proc (not Linux): RLIMIT_AS is left alone


def _cpu_used() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def lock_down(limits: WorkerLimits) -> dict[str, Any]:
    """Apply every layer to the calling process; see the module docstring.

    Returns:
        What is in force: ``{"nofile": 0, "nproc": 0, "as_bytes": ..., "cpu_hard": ...,
        "seccomp": bool, "uid": ...}``.
    """
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    baseline = _vm_size_bytes()
    as_bytes = baseline + limits.memory_bytes if baseline is not None else None
    os.closerange(3, 1 << 20)
    resource.setrlimit(resource.RLIMIT_NOFILE, (0, 0))
    resource.setrlimit(resource.RLIMIT_NPROC, (0, 0))
    resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0))
    if as_bytes is not None:
        resource.setrlimit(resource.RLIMIT_AS, (as_bytes, as_bytes))
    hard = max(1, limits.cpu_seconds_total)
    soft = min(hard, int(_cpu_used()) + 1 + limits.cpu_seconds_per_call)
    resource.setrlimit(resource.RLIMIT_CPU, (soft, hard))
    _cpu_limit[:] = [soft, hard]
    uid = os.getuid()  # before the filter: getuid is not on the allow-list
    seccomp = False
    if limits.seccomp and seccomp_supported():
        install_seccomp()
        seccomp = True
    return {"nofile": 0, "nproc": 0, "as_bytes": as_bytes, "cpu_hard": hard, "seccomp": seccomp, "uid": uid}


def arm_cpu(per_call: int) -> None:
    """Give the next call at least ``per_call`` CPU seconds before SIGXCPU (capped by the hard limit)."""
    soft, hard = _cpu_limit
    want = min(hard, int(_cpu_used()) + 1 + per_call)
    # Soft limits only grow here, so most calls skip the syscall (no CPU second crossed).
    if want > soft:
        resource.setrlimit(resource.RLIMIT_CPU, (want, hard))
        _cpu_limit[0] = want


_cpu_limit = [0, 0]
"""Soft and hard RLIMIT_CPU as last set by this module (saves a getrlimit per call)."""
