"""Evaluate unpublished candidates without touching the real registry.

Learners score many candidate artifacts; publishing each to the robot's registry would fill
it with versions nobody gates. :class:`ScratchRegistryEvaluator` keeps a private
:class:`~capevo.registry.local.LocalRegistry` (a temporary directory by default), mirrors
into it the versions of the real registry an evaluation needs, publishes each candidate
there, and runs any :class:`~capevo.runtime.evaluation.Evaluator` (e.g.
:class:`~capevo.runtime.evaluator.LocalEvaluator`) over that mirror. It implements
:class:`~capevo.learner.base.CandidateEvaluator`.

Invariants:
1. The real registry is only read (``get_version``, ``get_artifact``); nothing is published,
   promoted or recorded in it.
2. A mirrored version keeps the real version's kind, descriptor, interface, origin and
   artifact bytes; an override keeps all of that but the bytes (and the origin when
   ``override_origin`` is given), so trust and the termination predicates are the same.
3. Returned outcomes name the real registry's versions in ``capability_set``; an overridden
   ECM is reported at the version it overrides.
4. Each distinct artifact is published to the scratch registry once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from capevo.errors import Invalid
from capevo.records import EcmVersion, Origin, PublishSpec
from capevo.registry.api import Registry
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluation import EpisodeOutcome, Evaluator
from capevo.runtime.tasks import task_spec

SCRATCH_ACTOR = "capevo-learner-scratch"


class ScratchRegistryEvaluator:
    """A :class:`CandidateEvaluator` over a private mirror of ``source``.

    Args:
        source: The real registry (read only).
        make_evaluator: Builds the evaluator that runs episodes, given the scratch registry;
            called once.
        root: Directory of the scratch registry; default a temporary one, removed on close.

    Raises:
        Unavailable: the scratch registry cannot be created.
    """

    def __init__(
        self,
        source: Registry,
        make_evaluator: Callable[[Registry], Evaluator],
        *,
        root: str | Path | None = None,
    ) -> None:
        self.source = source
        self._tmp = None if root is not None else tempfile.mkdtemp(prefix="capevo-scratch-")
        self.root = Path(root) if root is not None else Path(self._tmp or "")
        self.scratch = LocalRegistry(self.root / "registry", actor=SCRATCH_ACTOR)
        self.inner = make_evaluator(self.scratch)
        self._published: dict[tuple[str, str, str], int] = {}

    def _put(self, record: EcmVersion, artifact: bytes, origin: Origin) -> int:
        sha = hashlib.sha256(artifact).hexdigest()
        key = (record.name, sha, origin.value)
        held = self._published.get(key)
        if held is not None:
            return held
        spec = PublishSpec(
            kind=record.kind,
            descriptor=record.descriptor,
            interface=record.interface,
            media_type=record.artifact.media_type,
            origin=origin,
            provenance=record.provenance,
        )
        version = self.scratch.publish(record.name, artifact, spec).version
        self._published[key] = version
        return version

    def evaluate(
        self,
        task: str,
        versions: Mapping[str, int],
        seeds: Sequence[int],
        *,
        overrides: Mapping[str, bytes] | None = None,
        override_origin: Origin | None = None,
    ) -> list[EpisodeOutcome]:
        """Run one episode per seed; ``overrides`` replace the named ECMs' artifacts.

        Raises:
            Invalid: an override or pinned version names an ECM outside the task's plan.
            NotFound: an ECM has no active version in ``source`` and none was given.
        """
        spec = task_spec(task)
        overrides = dict(overrides or {})
        outside = sorted((set(overrides) | set(versions)) - set(spec.ecm_names))
        if outside:
            raise Invalid(
                f"ECM(s) {', '.join(outside)} are not in the plan of task {spec.name!r}",
                details={"field": "overrides", "outside": outside},
            )
        pinned: dict[str, int] = {}
        real: dict[str, int] = {}
        for name in spec.ecm_names:
            record = self.source.get_version(name, versions.get(name))
            real[name] = record.version
            if name in overrides:
                pinned[name] = self._put(record, overrides[name], override_origin or record.origin)
            else:
                pinned[name] = self._put(record, self.source.get_artifact(name, record.version), record.origin)
        outcomes = self.inner.evaluate(spec.name, pinned, seeds)
        return [dataclasses.replace(o, capability_set=dict(real)) for o in outcomes]

    def close(self) -> None:
        """Close the inner evaluator and the scratch registry; remove a temporary root."""
        close = getattr(self.inner, "close", None)
        if callable(close):
            close()
        self.scratch.close()
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __enter__(self) -> ScratchRegistryEvaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
