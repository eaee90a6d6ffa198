"""The identity hash of the persistent agent: what must not change while capabilities evolve.

``identity_hash = sha256(canonical_json({"policy": {"type": <π_A class name>, "parameters":
<θ record>}, "identity": <M_id document>}))`` with canonical JSON = sorted keys, no spaces,
UTF-8, NaN refused (:func:`capevo.records.audit.canonical_json`). Episodic memory is not part
of it: the agent remembers more every episode without becoming someone else.

Invariants:
1. The hash depends only on π_A's class name, its parameters record and M_id's document:
   equal inputs give equal hashes across processes and loads; key order in the YAML does not matter.
2. Any change of a parameter value, of the policy class, or of any goal, belief or
   decomposition changes the hash.
3. :func:`changed_paths` names every dotted path where two documents differ.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any

from capevo.agent.base import AgentPolicy
from capevo.agent.identity import IdentityMemory
from capevo.records.audit import canonical_json


def policy_document(policy: AgentPolicy) -> dict[str, Any]:
    """``{"type": class name, "parameters": θ record}``: the policy's share of the identity hash."""
    return {"type": type(policy).__name__, "parameters": policy.parameters.to_dict()}


@dataclass(frozen=True, slots=True, kw_only=True)
class Fingerprint:
    """The identity hash and the documents it was computed from (JSON-copied, so detached)."""

    hash: str
    policy: dict[str, Any]
    identity: dict[str, Any]


def fingerprint(policy: AgentPolicy, identity: IdentityMemory) -> Fingerprint:
    """Hash π_A (type and parameters) together with M_id.

    Raises:
        ValueError: a parameter is not JSON-able or not finite (a broken policy record).
    """
    body = {"policy": policy_document(policy), "identity": identity.to_dict()}
    text = canonical_json(body)
    detached = json.loads(text)
    return Fingerprint(
        hash=hashlib.sha256(text.encode()).hexdigest(), policy=detached["policy"], identity=detached["identity"]
    )


def identity_hash(policy: AgentPolicy, identity: IdentityMemory) -> str:
    """sha256 hex digest of π_A's type and parameters together with M_id (see the module docstring)."""
    return fingerprint(policy, identity).hash


def changed_paths(before: Any, after: Any, prefix: str = "") -> list[str]:
    """Dotted paths (``decompositions.pick[1]``) where ``after`` differs from ``before``."""
    if isinstance(before, dict) and isinstance(after, dict):
        out: list[str] = []
        for key in sorted(set(before) | set(after), key=str):
            path = f"{prefix}.{key}" if prefix else str(key)
            if key not in before or key not in after:
                out.append(path)
            else:
                out.extend(changed_paths(before[key], after[key], path))
        return out
    if isinstance(before, list) and isinstance(after, list) and len(before) == len(after):
        out = []
        for i, (b, a) in enumerate(zip(before, after, strict=True)):
            out.extend(changed_paths(b, a, f"{prefix}[{i}]"))
        return out
    if type(before) is not type(after) or before != after:
        return [prefix or "<document>"]
    return []
