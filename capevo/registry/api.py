"""The registry API that both :class:`LocalRegistry` and the Zenoh :class:`Client` implement.

One shared test suite runs over both (``tests/registry/test_contract.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

from capevo.records import (
    AuditEvent,
    CapabilitySet,
    EcmDetail,
    EcmSummary,
    EcmVersion,
    PublishSpec,
    VerifyReport,
)


@runtime_checkable
class Registry(Protocol):
    """Versioned ECM registry.

    ``version=None`` in reads means the active version. Mutations return the record as it
    is after the change; ``actor`` names who made it in the audit history (the
    implementation's default actor when None). On a secured Zenoh registry the recorded actor
    is the Zenoh-authenticated user whatever ``actor`` says; an operator's differing
    ``actor`` is kept beside it as ``on_behalf_of``, anyone else's is dropped. On an open
    registry ``actor`` is recorded as claimed, marked ``auth: open``. Every method raises
    only :class:`capevo.errors.CapevoError` subclasses.
    """

    def list_ecms(self) -> list[EcmSummary]: ...

    def get_ecm(self, name: str) -> EcmDetail: ...

    def get_version(self, name: str, version: int | None = None) -> EcmVersion: ...

    def get_artifact(self, name: str, version: int | None = None) -> bytes: ...

    def history(self, name: str) -> list[AuditEvent]: ...

    def capability_set(self, revision: int | None = None) -> CapabilitySet: ...

    def publish(self, name: str, artifact: bytes, spec: PublishSpec, *, actor: str | None = None) -> EcmVersion: ...

    def promote(
        self,
        name: str,
        version: int,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion: ...

    def rollback(
        self,
        name: str,
        to: int | None = None,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion: ...

    def deprecate(self, name: str, version: int, *, reason: str = "", actor: str | None = None) -> EcmVersion: ...

    def reject(self, name: str, version: int, *, reason: str = "", actor: str | None = None) -> EcmVersion: ...

    def record_gate(
        self, name: str, version: int, evidence: Mapping[str, Any], *, reason: str = "", actor: str | None = None
    ) -> EcmVersion: ...

    def verify(self) -> VerifyReport: ...

    def close(self) -> None: ...
