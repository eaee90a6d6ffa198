"""Running untrusted code skills: static validation plus a locked-down worker process.

Layers, outermost first (each holds even if the ones before it are bypassed):

1. :mod:`.validator` — AST allow-list: imports, names, attributes (no dunders, no file I/O).
2. :mod:`.namespace` — restricted builtins and an ``__import__`` that admits only the allow-list.
3. :mod:`.client` / :mod:`.worker` — a separate ``python -I`` process (spawned, never
   forked), scrubbed environment, own session, only stdin/stdout/stderr open; the host
   kills it on a wall-clock timeout and restarts it.
4. :mod:`.limits` — RLIMIT_NOFILE 0 (no new fd: no file, socket, pipe), RLIMIT_NPROC 0,
   RLIMIT_FSIZE 0, RLIMIT_AS, per-call RLIMIT_CPU, and a seccomp-bpf syscall allow-list.
"""

from __future__ import annotations

from capevo.runtime.sandbox.client import SandboxConfig, SandboxedSkill, SkillRaised, SkillStep, WorkerDied
from capevo.runtime.sandbox.limits import WorkerLimits
from capevo.runtime.sandbox.namespace import BadOutput, SkillModule, load_skill_module
from capevo.runtime.sandbox.validator import ALLOWED_IMPORTS, Violation, find_violations, validate_source

__all__ = [
    "ALLOWED_IMPORTS",
    "BadOutput",
    "SandboxConfig",
    "SandboxedSkill",
    "SkillModule",
    "SkillRaised",
    "SkillStep",
    "Violation",
    "WorkerDied",
    "WorkerLimits",
    "find_violations",
    "load_skill_module",
    "validate_source",
]
