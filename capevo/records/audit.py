"""Hash chaining of the audit history.

Invariants:
1. ``event_hash`` depends on every field of the event except ``hash`` itself, through
   canonical JSON (sorted keys, no whitespace), so any edit of a stored event changes it.
2. The first event's ``prev_hash`` is ``GENESIS``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from typing import Any

from capevo.records import AuditEvent

GENESIS = "0" * 64


def canonical_json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def event_hash(fields: Mapping[str, Any]) -> str:
    """sha256 over the event's fields, ``hash`` excluded (it may be absent or stale)."""
    body = {k: v for k, v in fields.items() if k != "hash"}
    return hashlib.sha256(canonical_json(body).encode()).hexdigest()


def chain_problems(events: Iterable[AuditEvent]) -> list[str]:
    """Every break in the chain, in order; an empty list means the chain verifies."""
    problems: list[str] = []
    prev = GENESIS
    expected_seq = 1
    for ev in events:
        d = ev.to_dict()
        if ev.seq != expected_seq:
            problems.append(f"audit event seq {ev.seq}: expected seq {expected_seq} (gap or reorder)")
        if ev.prev_hash != prev:
            problems.append(f"audit event seq {ev.seq}: prev_hash does not match the previous event's hash")
        if event_hash(d) != ev.hash:
            problems.append(f"audit event seq {ev.seq}: hash does not match its contents (tampered)")
        prev = ev.hash
        expected_seq = ev.seq + 1
    return problems
