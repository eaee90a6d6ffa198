"""Turn a registry version and its artifact bytes into a :class:`LoadedEcm`, by kind.

Loaders register per :class:`Kind` with :func:`register_loader`; :func:`make_loader`
looks one up. Code goes in-process or to a sandbox worker per the :class:`TrustPolicy`.

Invariants:
1. :func:`load_ecm` checks the artifact's sha256 against the record before anything reads
   it (:class:`Corrupt` on mismatch).
2. Untrusted code never runs in the host process: with the default policy, only
   ``manual`` code gets an in-process :class:`CodeSkill`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from capevo.errors import Corrupt, Invalid
from capevo.records import EcmVersion, Interface, Kind, Origin
from capevo.runtime.ecm.base import LoadedEcm
from capevo.runtime.ecm.code import CodeSkill
from capevo.runtime.ecm.neural import NeuralPolicy
from capevo.runtime.ecm.prompt import load_prompt
from capevo.runtime.ecm.trust import TrustPolicy
from capevo.runtime.sandbox.client import SandboxConfig, SandboxedSkill


@dataclass(frozen=True, slots=True, kw_only=True)
class LoadOptions:
    """Settings every loader receives.

    Args:
        trust: Which code origins run in-process.
        sandbox: How sandbox workers are started and limited.
        params_override: θ for code skills (replaces some of ``PARAMS``).
    """

    trust: TrustPolicy = field(default_factory=TrustPolicy)
    sandbox: SandboxConfig = field(default_factory=SandboxConfig)
    params_override: Mapping[str, Any] | None = None


Loader = Callable[[str, int, Origin, Interface, bytes, LoadOptions], LoadedEcm]
LOADERS: dict[Kind, Loader] = {}


def register_loader(kind: Kind) -> Callable[[Loader], Loader]:
    """Decorator: make ``fn`` the loader for ``kind``."""

    def deco(fn: Loader) -> Loader:
        LOADERS[kind] = fn
        return fn

    return deco


def make_loader(kind: Kind | str) -> Loader:
    """The loader for ``kind``.

    Raises:
        Invalid: unknown kind, listing the valid ones.
    """
    try:
        return LOADERS[Kind(kind)]
    except (ValueError, KeyError):
        valid = ", ".join(sorted(k.value for k in LOADERS))
        raise Invalid(f"no loader for kind {kind!r}; valid: {valid}") from None


@register_loader(Kind.CODE)
def _load_code(
    name: str, version: int, origin: Origin, interface: Interface, artifact: bytes, opts: LoadOptions
) -> LoadedEcm:
    try:
        source = artifact.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise Invalid(f"{name}@{version}: code artifact is not UTF-8: {exc}") from None
    return load_code(
        source,
        name=name,
        version=version,
        origin=origin,
        interface=interface,
        params_override=opts.params_override,
        trust=opts.trust,
        sandbox=opts.sandbox,
    )


@register_loader(Kind.NEURAL)
def _load_neural(
    name: str, version: int, origin: Origin, interface: Interface, artifact: bytes, opts: LoadOptions
) -> LoadedEcm:
    return load_neural(artifact, name=name, version=version, origin=origin, interface=interface)


@register_loader(Kind.PROMPT)
def _load_prompt(
    name: str, version: int, origin: Origin, interface: Interface, artifact: bytes, opts: LoadOptions
) -> LoadedEcm:
    text = load_prompt(artifact, name=f"{name}@{version}")
    return LoadedEcm(name=name, version=version, kind=Kind.PROMPT, origin=origin, interface=interface, text=text)


def load_ecm(record: EcmVersion, artifact: bytes, *, options: LoadOptions | None = None) -> LoadedEcm:
    """Load one registry version.

    Args:
        record: The version's record (kind, origin, interface, artifact hash).
        artifact: Its artifact bytes, e.g. from ``Registry.get_artifact``.
        options: Trust policy, sandbox config, θ override.

    Returns:
        The loaded ECM; close it when done (it may own a worker process).

    Raises:
        Corrupt: the bytes do not hash to ``record.artifact.sha256``.
        Invalid: the artifact does not load (bad zip, syntax error, interface mismatch ...).
        SandboxViolation: code that breaks the sandbox rules.
    """
    digest = hashlib.sha256(artifact).hexdigest()
    if digest != record.artifact.sha256:
        raise Corrupt(
            f"{record.name}@{record.version}: artifact sha256 {digest} does not match the record's "
            f"{record.artifact.sha256}"
        )
    loader = make_loader(record.kind)
    return loader(record.name, record.version, record.origin, record.interface, artifact, options or LoadOptions())


def load_code(
    source: str,
    *,
    name: str,
    version: int = 0,
    origin: Origin = Origin.MANUAL,
    interface: Interface | None = None,
    params_override: Mapping[str, Any] | None = None,
    trust: TrustPolicy | None = None,
    sandbox: SandboxConfig | None = None,
) -> LoadedEcm:
    """A code ECM from source, in-process or sandboxed per ``trust`` and ``origin``.

    Raises:
        SandboxViolation, Invalid: as :class:`CodeSkill` / :class:`SandboxedSkill`.
    """
    policy = trust or TrustPolicy()
    filename = f"<{name}@{version}>"
    runner: CodeSkill | SandboxedSkill
    if policy.runs_in_process(Kind.CODE, origin):
        runner = CodeSkill(source, params_override, filename=filename)
    else:
        runner = SandboxedSkill(source, params_override, config=sandbox, filename=filename)
    return LoadedEcm(
        name=name, version=version, kind=Kind.CODE, origin=origin, interface=interface or Interface(), runner=runner
    )


def load_neural(
    artifact: bytes, *, name: str, version: int = 0, origin: Origin = Origin.RL, interface: Interface
) -> LoadedEcm:
    """A neural ECM from SB3 model-zip bytes (CPU, deterministic, no unpickling).

    Raises:
        Invalid: unsupported artifact or interface mismatch.
    """
    runner = NeuralPolicy(artifact, inputs=interface.inputs, outputs=interface.outputs, name=f"{name}@{version}")
    return LoadedEcm(name=name, version=version, kind=Kind.NEURAL, origin=origin, interface=interface, runner=runner)
