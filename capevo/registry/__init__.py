"""The versioned ECM registry: records, the in-process registry, the Zenoh service and client.

``LocalRegistry`` and ``Client`` implement the same :class:`Registry` protocol; use
:func:`open_registry` to get either from a ``--root`` or a ``--connect`` endpoint.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from capevo._lazy import lazy_getattr

if TYPE_CHECKING:
    from capevo.records import (
        Action,
        ArtifactRef,
        AuditEvent,
        CapabilitySet,
        Descriptor,
        EcmDetail,
        EcmSummary,
        EcmVersion,
        Interface,
        IOSpec,
        Kind,
        Origin,
        Predicate,
        Provenance,
        PublishSpec,
        State,
        VerifyReport,
    )
    from capevo.registry.api import Registry
    from capevo.registry.client import Client
    from capevo.registry.descriptor import dump_publish_spec, parse_publish_spec
    from capevo.registry.local import LocalRegistry
    from capevo.registry.open import open_registry
    from capevo.registry.service import serve

_HOMES = {
    "Registry": "capevo.registry.api",
    "Client": "capevo.registry.client",
    "LocalRegistry": "capevo.registry.local",
    "open_registry": "capevo.registry.open",
    "serve": "capevo.registry.service",
    "parse_publish_spec": "capevo.registry.descriptor",
    "dump_publish_spec": "capevo.registry.descriptor",
    **{
        name: "capevo.records"
        for name in (
            "Action",
            "ArtifactRef",
            "AuditEvent",
            "CapabilitySet",
            "Descriptor",
            "EcmDetail",
            "EcmSummary",
            "EcmVersion",
            "IOSpec",
            "Interface",
            "Kind",
            "Origin",
            "Predicate",
            "Provenance",
            "PublishSpec",
            "State",
            "VerifyReport",
        )
    },
}
__all__ = [
    "Action",
    "ArtifactRef",
    "AuditEvent",
    "CapabilitySet",
    "Client",
    "Descriptor",
    "EcmDetail",
    "EcmSummary",
    "EcmVersion",
    "IOSpec",
    "Interface",
    "Kind",
    "LocalRegistry",
    "Origin",
    "Predicate",
    "Provenance",
    "PublishSpec",
    "Registry",
    "State",
    "VerifyReport",
    "dump_publish_spec",
    "open_registry",
    "parse_publish_spec",
    "serve",
]
__getattr__ = lazy_getattr(__name__, _HOMES)
