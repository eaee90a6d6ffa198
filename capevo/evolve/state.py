"""What a run keeps on disk to resume: the manifest (``run.json``) and the phase journal.

The manifest fixes what must not change under a resumed run: the task, the modality, the
base seed, the configuration (except the number of iterations) and the agent's identity
hash. The journal (``journal.jsonl``, one fsynced line per event) records how far the
current iteration got, so a redone iteration neither learns a second candidate for a
decision already taken nor gates the same candidate twice:

* ``start``: iteration i began with capability set C (its live episodes run exactly C);
* ``candidate``: iteration i published (or adopted) candidate v of ECM e;
* ``decided``: the gate decided on it (the evidence itself is in the registry);
* ``final``: the final evaluation ran (outcomes included).

Invariants:
1. :meth:`RunManifest.check_resume` raises :class:`IdentityViolation` when the agent's identity
   hash differs from the one the run started with, and :class:`Invalid` naming every other
   field that differs (task, modality, seed, perturbations, mode, registry, learner, config;
   ``config.iterations`` excepted).
2. :meth:`Journal.attempt` returns the events of the latest attempt of an iteration only
   (those after its last ``start``).
3. A journal event whose append returned survives a SIGKILL; a torn last line is ignored.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.errors import IdentityViolation, Invalid
from capevo.evolve.config import EvolveConfig
from capevo.evolve.metrics import append_durably, canonical_line, repair_jsonl, write_atomically

MANIFEST = "run.json"
JOURNAL = "journal.jsonl"
FORMAT = "capevo.evolve/1"


@dataclass(frozen=True, slots=True, kw_only=True)
class RunManifest:
    """The fixed facts of one evolution run."""

    task: str
    modality: str
    seed: int
    perturbations: bool
    config: EvolveConfig
    identity_hash: str
    mode: str
    """``embedded`` (local registry, in-process runtime) or ``connect``."""
    registry: str
    """Where the registry is: a directory or the Zenoh endpoints."""
    learner: str
    """``local`` (in process) or ``remote`` (candidates published by learner workers)."""
    created_at: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "task": self.task,
            "modality": self.modality,
            "seed": self.seed,
            "perturbations": self.perturbations,
            "config": self.config.to_dict(),
            "identity_hash": self.identity_hash,
            "mode": self.mode,
            "registry": self.registry,
            "learner": self.learner,
            "created_at": self.created_at,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RunManifest:
        """Inverse of :meth:`to_dict`.

        Raises:
            Invalid: not a manifest of this format.
        """
        if d.get("format") != FORMAT:
            raise Invalid(f"not an evolve run manifest (format {d.get('format')!r})", details={"field": "format"})
        try:
            return cls(
                task=str(d["task"]),
                modality=str(d["modality"]),
                seed=int(d["seed"]),
                perturbations=bool(d["perturbations"]),
                config=EvolveConfig.from_dict(d["config"]),
                identity_hash=str(d["identity_hash"]),
                mode=str(d["mode"]),
                registry=str(d["registry"]),
                learner=str(d.get("learner", "local")),
                created_at=float(d["created_at"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise Invalid(f"bad evolve run manifest: {exc}", details={"field": "manifest"}) from None

    def check_resume(self, other: RunManifest) -> None:
        """Refuse to continue this run as ``other`` describes it (see invariant 1).

        Raises:
            IdentityViolation: the agent's identity hash changed.
            Invalid: the task, modality, seed, perturbations or configuration changed.
        """
        if other.identity_hash != self.identity_hash:
            raise IdentityViolation(
                f"the agent's identity changed since this run started: identity hash {other.identity_hash[:16]}... "
                f"!= {self.identity_hash[:16]}... recorded in {MANIFEST}; a run cannot continue with another agent",
                details={"expected_hash": self.identity_hash, "actual_hash": other.identity_hash},
            )
        differ = [
            name
            for name in ("task", "modality", "seed", "perturbations", "mode", "registry", "learner")
            if getattr(self, name) != getattr(other, name)
        ]
        differ += [f"config.{k}" for k in self.config.resume_mismatches(other.config)]
        if differ:
            shown = "; ".join(f"{k}: {_get(self, k)!r} -> {_get(other, k)!r}" for k in differ)
            raise Invalid(
                f"this report directory holds a run with other settings ({shown}); use another --report-dir, "
                "or the original settings to resume",
                details={"field": differ[0], "differ": differ},
            )


def _get(m: RunManifest, dotted: str) -> Any:
    if dotted.startswith("config."):
        return m.config.to_dict().get(dotted.split(".", 1)[1])
    return getattr(m, dotted)


def load_manifest(directory: Path) -> RunManifest | None:
    """The manifest in ``directory``, or None when there is none.

    Raises:
        Invalid: the file is not a manifest.
    """
    path = directory / MANIFEST
    if not path.exists():
        return None
    import json

    try:
        return RunManifest.from_dict(json.loads(path.read_text()))
    except ValueError as exc:
        raise Invalid(f"{path}: not JSON: {exc}", details={"path": str(path)}) from None


def save_manifest(directory: Path, manifest: RunManifest) -> None:
    """Write ``run.json`` atomically."""
    import json

    write_atomically(directory / MANIFEST, (json.dumps(manifest.to_dict(), indent=2) + "\n").encode())


class Journal:
    """The phase journal of a run (see the module docstring).

    Args:
        directory: The report directory.
    """

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.path = Path(directory) / JOURNAL
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._events = repair_jsonl(self.path)

    @property
    def events(self) -> list[dict[str, Any]]:
        return list(self._events)

    def write(self, event: str, iteration: int, **fields: Any) -> dict[str, Any]:
        """Append one event durably and return it."""
        record = {"event": event, "iteration": iteration, "at": time.time(), **fields}
        append_durably(self.path, canonical_line(record))
        self._events.append(record)
        return record

    def attempt(self, iteration: int) -> list[dict[str, Any]]:
        """The events of the latest attempt at ``iteration`` (from its last ``start`` on)."""
        mine = [e for e in self._events if e.get("iteration") == iteration]
        starts = [i for i, e in enumerate(mine) if e.get("event") == "start"]
        return mine[starts[-1] :] if starts else mine

    def last(self, iteration: int, event: str) -> dict[str, Any] | None:
        """The latest ``event`` of ``iteration``'s latest attempt, or None."""
        found = [e for e in self.attempt(iteration) if e.get("event") == event]
        return found[-1] if found else None

    def final(self) -> dict[str, Any] | None:
        """The latest ``final`` event, or None."""
        found = [e for e in self._events if e.get("event") == "final"]
        return found[-1] if found else None


__all__ = ["FORMAT", "JOURNAL", "MANIFEST", "Journal", "RunManifest", "load_manifest", "save_manifest"]
