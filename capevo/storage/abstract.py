"""The abstract metadata store: what the registry needs from a database, nothing more.

Methods are grouped by entity and return records, never rows. Each mutating method is
one atomic transaction: it reads the current state, checks the lifecycle rule
(:func:`capevo.records.lifecycle.check_transition`), writes, and appends the hash-chained
audit event, all or nothing. That is what keeps version numbers gap-free under concurrent
publishers and makes ``expected_active`` a real compare-and-swap.

A networked database can replace SQLite by implementing this class; the blob bytes live
in a :class:`capevo.storage.blobs.BlobStore`, not here.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from typing import Any

from capevo.records import (
    ArtifactRef,
    Attribution,
    AuditEvent,
    CapabilitySet,
    EcmDetail,
    EcmSummary,
    EcmVersion,
    Mutation,
    PublishSpec,
)


class AbstractStore(abc.ABC):
    """Metadata and history of every ECM. Implementations must be safe to call from many threads.

    Every mutation takes ``actor``: a name, or an :class:`Attribution` whose ``actor`` is
    recorded as the event's actor (and a new version's ``created_by``) and whose
    :meth:`~Attribution.audit_data` is added to the event's ``data``.
    """

    # --- ECMs -------------------------------------------------------------------------
    @abc.abstractmethod
    def list_ecms(self) -> list[EcmSummary]:
        """Every ECM, sorted by name."""

    @abc.abstractmethod
    def get_ecm(self, name: str) -> EcmDetail:
        """One ECM with all its versions. Raises NotFound."""

    # --- versions ---------------------------------------------------------------------
    @abc.abstractmethod
    def create_version(
        self, name: str, spec: PublishSpec, artifact: ArtifactRef, *, actor: str | Attribution
    ) -> Mutation:
        """Add the next version (max + 1, or 0) as a candidate and log ``publish``.

        Raises:
            NotFound: ``spec.parent`` names a version that does not exist.
        """

    @abc.abstractmethod
    def get_version(self, name: str, version: int) -> EcmVersion:
        """Raises NotFound."""

    @abc.abstractmethod
    def get_active(self, name: str) -> EcmVersion:
        """The version the active pointer names. Raises NotFound if none is active."""

    @abc.abstractmethod
    def record_gate(
        self, name: str, version: int, evidence: Mapping[str, Any], *, actor: str | Attribution, reason: str = ""
    ) -> Mutation:
        """Store gate evidence on a candidate and log ``gate``. Raises NotFound, IllegalTransition."""

    @abc.abstractmethod
    def set_state(
        self, name: str, version: int, action: str, *, actor: str | Attribution, reason: str = ""
    ) -> Mutation:
        """Apply ``reject`` or ``deprecate`` to one version and log it."""

    @abc.abstractmethod
    def move_active(
        self,
        name: str,
        version: int | None,
        action: str,
        *,
        expected_active: int | None = None,
        actor: str | Attribution,
        reason: str = "",
    ) -> Mutation:
        """Point ``name``'s active pointer at ``version`` (``promote`` or ``rollback``).

        The old active version becomes superseded, the registry revision goes up by one,
        and the event is logged, in one transaction. For ``rollback`` with ``version``
        None, the target is the version that was active before the current one.

        Raises:
            Conflict: ``expected_active`` was given and is not the current active version.
            IllegalTransition: the target's state does not allow ``action``.
            NotFound: no such ECM or version, or nothing to roll back to.
        """

    # --- capability set ---------------------------------------------------------------
    @abc.abstractmethod
    def capability_set(self, revision: int | None = None) -> CapabilitySet:
        """C at ``revision`` (default: now). Raises NotFound for a revision not yet reached."""

    # --- history ----------------------------------------------------------------------
    @abc.abstractmethod
    def history(self, name: str | None = None) -> list[AuditEvent]:
        """Audit events in order; all of them when ``name`` is None."""

    @abc.abstractmethod
    def artifact_refs(self) -> list[ArtifactRef]:
        """Every artifact any version references (for ``verify``)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release connections. Idempotent."""
