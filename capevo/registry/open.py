"""One way for the CLI (and anyone) to get a :class:`Registry`: local directory or Zenoh.

Invariants:
1. Exactly one of ``root`` and ``connect`` must be given; anything else is :class:`Invalid`.
2. The returned object satisfies :class:`capevo.registry.api.Registry`; the caller closes it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from capevo.errors import Invalid
from capevo.registry.api import Registry
from capevo.registry.keys import DEFAULT_NAMESPACE
from capevo.registry.zconfig import split_endpoints


def open_registry(
    *,
    root: str | os.PathLike[str] | None = None,
    connect: Sequence[str] | str | None = None,
    namespace: str = DEFAULT_NAMESPACE,
    user: str | None = None,
    password: str | None = None,
    timeout: float = 10.0,
    actor: str | None = None,
) -> Registry:
    """Open the registry at ``root`` (in-process) or the one reachable via ``connect`` (Zenoh).

    Args:
        root: Registry directory for a :class:`LocalRegistry`.
        connect: Zenoh endpoint(s) of a registry server, e.g. ``tcp/127.0.0.1:7447``.
        namespace, user, password, timeout: Zenoh client settings (ignored for ``root``).
        actor: Who mutations are attributed to in the audit log.

    Returns:
        A registry; close it when done (both kinds are context managers).

    Raises:
        Invalid: neither or both of root/connect, or credentials given with ``root``.
        Unavailable: the directory or the server cannot be reached.
    """
    endpoints = split_endpoints(connect)
    if (root is None) == (not endpoints):
        raise Invalid(
            "give exactly one of root (a local registry directory) or connect (a Zenoh registry endpoint)",
            details={"field": "root"},
        )
    if root is not None:
        if user is not None or password is not None:
            raise Invalid(
                "user/password apply to a Zenoh registry (connect), not to a local root", details={"field": "user"}
            )
        from capevo.registry.local import LocalRegistry

        return LocalRegistry(root, actor=actor)
    from capevo.registry.client import Client

    return Client(endpoints, namespace=namespace, user=user, password=password, timeout=timeout, actor=actor)
