"""The ECM versions a runtime executes for one task: resolved, fetched, checked, loaded, hot-swapped.

:class:`LoadedCapabilitySet` takes any :class:`~capevo.registry.api.Registry` (a local
directory or the Zenoh client), resolves the registry's capability set, fetches the artifact
of each ECM the task's decomposition needs (through an :mod:`artifact cache
<capevo.runtime.artifact_cache>`, so a restart or a registry outage does not re-download),
checks that the versions compose (:func:`check_plan`), and loads them with the ECM loaders.

Hot swap: :meth:`LoadedCapabilitySet.queue_swap` (callable from any thread, e.g. a registry
event callback) only records the wish; :meth:`LoadedCapabilitySet.begin_episode`, which the
episode loop calls before it resets the environment, applies it. An ECM is therefore never
replaced in the middle of its execution, nor in the middle of an episode.

Recovery (what the invoker does when a call fails, see :mod:`capevo.runtime.ecm.recovery`),
by name: ``abort`` (hold still), ``retry`` (call once more, then hold still), ``fallback``
(call the previous version, then hold still) and ``retry-fallback``. The previous version is
the one a hot swap replaced (kept loaded for this), else, with a fallback mode, the version
that was active before the current one, loaded at start.

Invariants:
1. After construction and after every :meth:`begin_episode`, every ECM of the plan is loaded
   at exactly one version, and the plan passes :func:`check_plan`.
2. :meth:`queue_swap` and :meth:`refresh` never change the loaded set; only
   :meth:`begin_episode` does.
3. A swap whose fetch, load or composition check fails leaves the loaded set unchanged. A
   failure to reach the registry (:class:`Unavailable`, :class:`Timeout`) keeps the swap
   pending for the next episode; any other failure drops it and is reported.
4. Every artifact is checked against its record's sha256 before it is loaded, whether it
   came from the registry or from the cache.
5. Explicitly given ``versions`` are pinned: :meth:`refresh` never queues a swap for them.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from capevo.errors import CapevoError, Invalid, NotFound, Timeout, Unavailable, check_choice
from capevo.records import CapabilitySet, EcmVersion, Interface, Kind, State
from capevo.registry.api import Registry
from capevo.registry.predicates import missing_signals
from capevo.runtime.artifact_cache import ArtifactStore, MemoryArtifactCache
from capevo.runtime.ecm import (
    EcmInvoker,
    Fallback,
    LoadedEcm,
    LoadOptions,
    RecoveryStrategy,
    Retry,
    SafeAbort,
    check_pair,
    load_ecm,
    output_size,
)
from capevo.runtime.tasks import TaskSpec, task_spec

log = logging.getLogger(__name__)

RECOVERY_MODES: tuple[str, ...] = ("abort", "retry", "fallback", "retry-fallback")
DEFAULT_RECOVERY = "retry"
_RETRYABLE = (Unavailable, Timeout)


def check_recovery_mode(mode: str) -> str:
    """Return ``mode`` if it is one of :data:`RECOVERY_MODES`.

    Raises:
        Invalid: naming the valid modes.
    """
    return check_choice(mode, RECOVERY_MODES, what="recovery mode", field="recovery")


def _label(record: EcmVersion) -> str:
    return f"{record.name}@{record.version}"


def _plan_error(position: int, record: EcmVersion, message: str, field: str, **extra: Any) -> Invalid:
    label = _label(record)
    return Invalid(
        f"plan step {position} ({label}): {message}",
        details={"position": position, "ecm": label, "field": field, **extra},
    )


def check_plan(
    spec: TaskSpec,
    records: Sequence[EcmVersion],
    *,
    observation_shapes: Mapping[str, Sequence[int]] | None = None,
) -> None:
    """Check that ``records`` (in decomposition order) can run task ``spec`` one after another.

    For each ECM: it is executable (not a prompt); its outputs, if declared, make one action of
    the task's dimension; its applicability and termination predicates use only the task's
    signals; each declared input is either an observation of the task (with the observation's
    shape, when ``observation_shapes`` is given) or, composing ``c_i ∘ c_j``, an output of the
    ECM before it (:func:`capevo.runtime.ecm.check_pair`: name, shape, dtype, bounds).

    Args:
        spec: The task.
        records: One version per plan step, in order.
        observation_shapes: The environment's observation keys and their shapes; without it,
            ``spec.observation_keys`` are the observation names and shapes are not checked.

    Raises:
        Invalid: the first problem, naming the plan step, the ECM (``name@version``) and the
            field; ``details`` has ``position``, ``ecm`` and ``field``.
    """
    signals = frozenset(spec.signal_names)
    env_keys = frozenset(observation_shapes) if observation_shapes is not None else frozenset(spec.observation_keys)
    for i, rec in enumerate(records):
        if rec.kind is Kind.PROMPT:
            raise _plan_error(i, rec, "a prompt ECM cannot be executed step by step", "kind")
        outputs = rec.interface.outputs
        if outputs and output_size(outputs) != spec.action_layout.dim:
            raise _plan_error(
                i,
                rec,
                f"outputs total {output_size(outputs)} values, but task {spec.name!r} takes actions of "
                f"{spec.action_layout.dim}",
                "interface.outputs",
                expected=spec.action_layout.dim,
                got=output_size(outputs),
            )
        for which in ("applicability", "termination"):
            lacking = missing_signals(getattr(rec.descriptor, which), signals)
            if lacking:
                raise _plan_error(
                    i,
                    rec,
                    f"{which} predicate uses signal(s) {', '.join(lacking)}, which task {spec.name!r} does not "
                    f"expose (it has: {', '.join(sorted(signals))})",
                    f"descriptor.{which}",
                    missing=lacking,
                )
        chained = []
        for s in rec.interface.inputs:
            if s.name not in env_keys:
                chained.append(s)
                continue
            if observation_shapes is not None:
                have = tuple(int(n) for n in observation_shapes[s.name])
                if have != tuple(s.shape):
                    raise _plan_error(
                        i,
                        rec,
                        f"input {s.name!r} has shape {list(s.shape)}, but the task's observation {s.name!r} "
                        f"has shape {list(have)}",
                        f"interface.inputs.{s.name}.shape",
                        expected=list(have),
                        got=list(s.shape),
                    )
        if not chained:
            continue
        if i == 0:
            raise _plan_error(
                i,
                rec,
                f"input {chained[0].name!r} is not an observation of task {spec.name!r} and no ECM runs before "
                f"this one to produce it (observations: {', '.join(sorted(env_keys))})",
                f"interface.inputs.{chained[0].name}",
            )
        consumer = dataclasses.replace(rec, interface=Interface(inputs=tuple(chained), outputs=outputs))
        try:
            check_pair(records[i - 1], consumer, position=i - 1)
        except Invalid as exc:
            raise Invalid(
                f"{exc.message} (and it is not an observation of task {spec.name!r})",
                details={**exc.details, "ecm": _label(rec)},
            ) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class SwapResult:
    """What :meth:`LoadedCapabilitySet.begin_episode` did with one queued swap."""

    name: str
    from_version: int
    to_version: int
    applied: bool
    error: str | None = None
    pending: bool = False
    """The swap failed for lack of the registry and stays queued."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "from_version": self.from_version,
            "to_version": self.to_version,
            "applied": self.applied,
            "error": self.error,
            "pending": self.pending,
        }


@dataclass(frozen=True, slots=True)
class _Pending:
    version: int
    record: EcmVersion | None
    revision: int | None


class LoadedCapabilitySet:
    """The loaded ECM versions of one task (see the module docstring).

    Args:
        registry: Where records and artifacts come from.
        task: Task id or name (``"T1"``, ``"pick"``).
        versions: ECM versions to run instead of the active ones (pinned); ECMs not named run
            at their active version.
        ecms: The plan's ECMs in order; default the task's decomposition.
        cache: Artifact cache; default an in-memory one.
        load_options: Trust policy and sandbox settings for the loaders.
        recovery: One of :data:`RECOVERY_MODES`.
        observation_shapes: The environment's observation shapes, for :func:`check_plan`.

    Raises:
        Invalid: unknown task or recovery mode, a pinned ECM outside the plan, a plan that
            does not compose, or an artifact that does not load.
        NotFound: an ECM of the plan has no active version and none was given.
        Corrupt: an artifact does not match its record's sha256.
        Unavailable, Timeout: the registry cannot be reached.
    """

    def __init__(
        self,
        registry: Registry,
        task: str,
        *,
        versions: Mapping[str, int] | None = None,
        ecms: Sequence[str] | None = None,
        cache: ArtifactStore | None = None,
        load_options: LoadOptions | None = None,
        recovery: str = DEFAULT_RECOVERY,
        observation_shapes: Mapping[str, Sequence[int]] | None = None,
    ) -> None:
        self._registry = registry
        self._spec = task_spec(task)
        self._names: tuple[str, ...] = tuple(ecms) if ecms is not None else self._spec.ecm_names
        if not self._names:
            raise Invalid(f"task {self._spec.name!r}: the plan names no ECM", details={"field": "ecms"})
        pinned = dict(versions or {})
        outside = sorted(set(pinned) - set(self._names))
        if outside:
            raise Invalid(
                f"ECM(s) {', '.join(outside)} are not in the plan of task {self._spec.name!r} "
                f"({', '.join(self._names)})",
                details={"field": "versions", "outside": outside},
            )
        self._pinned = pinned
        self._cache: ArtifactStore = cache if cache is not None else MemoryArtifactCache()
        self._options = load_options or LoadOptions()
        self._recovery = check_recovery_mode(recovery)
        self._shapes = (
            {k: tuple(int(n) for n in v) for k, v in observation_shapes.items()} if observation_shapes else None
        )
        self._lock = threading.Lock()
        self._pending: dict[str, _Pending] = {}
        self._closed = False

        cap = registry.capability_set()
        records = []
        for name in self._names:
            version = pinned.get(name, cap.active.get(name))
            if version is None:
                raise NotFound(
                    f"task {self._spec.name!r} needs ECM {name!r}, which has no active version at registry "
                    f"revision {cap.revision} (and no version was given)",
                    details={"field": "versions", "ecm": name, "revision": cap.revision},
                )
            records.append(registry.get_version(name, version))
        check_plan(self._spec, records, observation_shapes=self._shapes)
        self._revision: int = cap.revision
        self._records: dict[str, EcmVersion] = {}
        self._loaded: dict[str, LoadedEcm] = {}
        self._fallback: dict[str, LoadedEcm] = {}
        try:
            for record in records:
                self._loaded[record.name] = self._load(record)
                self._records[record.name] = record
            if "fallback" in self._recovery:
                for record in records:
                    self._preload_fallback(record)
        except BaseException:
            self.close()
            raise
        self._records_view = MappingProxyType(dict(self._records))

    # --- reading ------------------------------------------------------------------------

    @property
    def task(self) -> TaskSpec:
        return self._spec

    @property
    def names(self) -> tuple[str, ...]:
        """The plan's ECMs, in order."""
        return self._names

    @property
    def revision(self) -> int:
        """Registry revision at which the loaded versions were resolved (or last swapped)."""
        return self._revision

    @property
    def versions(self) -> dict[str, int]:
        """Loaded version of every ECM of the plan (a copy)."""
        with self._lock:
            return {name: self._records[name].version for name in self._names}

    @property
    def records(self) -> Mapping[str, EcmVersion]:
        """Loaded record of every ECM (read-only; a new mapping after each applied swap)."""
        return self._records_view

    @property
    def capability_set(self) -> CapabilitySet:
        """The loaded versions as a :class:`CapabilitySet` at :attr:`revision`."""
        return CapabilitySet(revision=self._revision, active=self.versions)

    @property
    def pinned(self) -> dict[str, int]:
        return dict(self._pinned)

    @property
    def recovery(self) -> str:
        return self._recovery

    def loaded(self, name: str) -> LoadedEcm:
        """The loaded ECM ``name``.

        Raises:
            NotFound: ``name`` is not in the plan.
        """
        try:
            return self._loaded[name]
        except KeyError:
            raise NotFound(
                f"ECM {name!r} is not loaded (loaded: {', '.join(self._names)})", details={"ecm": name}
            ) from None

    def fallback(self, name: str) -> LoadedEcm | None:
        """The version recovery falls back to for ``name``, if one is loaded."""
        return self._fallback.get(name)

    def pending(self) -> dict[str, int]:
        """Queued swaps: ECM name -> version."""
        with self._lock:
            return {name: p.version for name, p in self._pending.items()}

    # --- executing ----------------------------------------------------------------------

    def make_recovery(self, name: str) -> RecoveryStrategy:
        """The recovery strategy for one activation of ``name``, per :attr:`recovery`."""
        fallback = self._fallback.get(name)
        tail: RecoveryStrategy = SafeAbort()
        if "fallback" in self._recovery and fallback is not None:
            tail = Fallback(alternatives=[fallback])
        if self._recovery.startswith("retry"):
            return Retry(attempts=1, then=tail)
        return tail

    def make_invoker(
        self, name: str, *, step_budget: int | None, timeout_s: float, default_gripper: float = 0.0
    ) -> EcmInvoker:
        """A fresh invoker for one activation of ``name`` (budget and recovery state start at zero).

        Raises:
            NotFound: ``name`` is not in the plan. Invalid: bad budget or timeout.
        """
        return EcmInvoker(
            self.loaded(name),
            layout=self._spec.action_layout,
            timeout_s=timeout_s,
            step_budget=step_budget,
            recovery=self.make_recovery(name),
            default_gripper=default_gripper,
        )

    # --- swapping -----------------------------------------------------------------------

    def queue_swap(
        self, name: str, version: int, *, record: EcmVersion | None = None, revision: int | None = None
    ) -> None:
        """Ask for ``name`` to run at ``version`` from the next episode on; a later call wins.

        Args:
            name: An ECM of the plan.
            version: The version to load.
            record: Its record, if the caller has it (saves a registry round trip).
            revision: The registry revision the change belongs to.

        Raises:
            Invalid: ``name`` is not in the plan, or ``record`` is not that version.
        """
        if name not in self._names:
            raise Invalid(
                f"cannot swap {name!r}: not in the plan of task {self._spec.name!r} ({', '.join(self._names)})",
                details={"field": "name"},
            )
        if record is not None and (record.name != name or record.version != version):
            raise Invalid(f"record {_label(record)} is not {name}@{version}", details={"field": "record"})
        with self._lock:
            self._pending[name] = _Pending(version=int(version), record=record, revision=revision)

    def refresh(self) -> dict[str, int]:
        """Queue a swap for every unpinned ECM whose active version in the registry differs.

        Returns:
            The swaps queued: ECM name -> version.

        Raises:
            Unavailable, Timeout: the registry cannot be reached (nothing is queued).
        """
        cap = self._registry.capability_set()
        queued: dict[str, int] = {}
        current = self.versions
        for name in self._names:
            if name in self._pinned:
                continue
            active = cap.active.get(name)
            if active is not None and active != current[name]:
                self.queue_swap(name, active, revision=cap.revision)
                queued[name] = active
        if not queued:
            with self._lock:
                if not self._pending:
                    self._revision = max(self._revision, cap.revision)
        return queued

    def begin_episode(self) -> list[SwapResult]:
        """Apply the queued swaps (the episode loop calls this before each episode).

        Returns:
            One result per queued swap that named a version other than the loaded one.
        """
        with self._lock:
            pending = dict(self._pending)
            self._pending.clear()
        results: list[SwapResult] = []
        for name, p in pending.items():
            current = self._records[name]
            if p.version == current.version:
                if p.revision is not None:
                    self._revision = max(self._revision, p.revision)
                continue
            results.append(self._apply(name, current, p))
        return results

    def _apply(self, name: str, current: EcmVersion, p: _Pending) -> SwapResult:
        def result(*, applied: bool, error: str | None = None, pending: bool = False) -> SwapResult:
            return SwapResult(
                name=name,
                from_version=current.version,
                to_version=p.version,
                applied=applied,
                error=error,
                pending=pending,
            )

        try:
            record = p.record if p.record is not None else self._registry.get_version(name, p.version)
            plan = [record if n == name else self._records[n] for n in self._names]
            check_plan(self._spec, plan, observation_shapes=self._shapes)
            loaded = self._load(record)
        except _RETRYABLE as exc:
            with self._lock:
                self._pending.setdefault(name, p)
            log.warning("swap %s %d -> %d deferred: %s", name, current.version, p.version, exc)
            return result(applied=False, error=str(exc), pending=True)
        except CapevoError as exc:
            log.error("swap %s %d -> %d refused: %s", name, current.version, p.version, exc)
            return result(applied=False, error=str(exc))
        old = self._loaded[name]
        previous_fallback = self._fallback.get(name)
        with self._lock:
            self._records[name] = record
            self._loaded[name] = loaded
            # The replaced version is the natural fallback: it ran until a moment ago.
            self._fallback[name] = old
            if p.revision is not None:
                self._revision = max(self._revision, p.revision)
            self._records_view = MappingProxyType(dict(self._records))
        if previous_fallback is not None and previous_fallback is not loaded:
            previous_fallback.close()
        log.info("swapped %s %d -> %d", name, current.version, record.version)
        return result(applied=True)

    # --- loading ------------------------------------------------------------------------

    def _artifact(self, record: EcmVersion) -> bytes:
        return self._cache.fetch(
            record.artifact.sha256, lambda: self._registry.get_artifact(record.name, record.version)
        )

    def _load(self, record: EcmVersion) -> LoadedEcm:
        return load_ecm(record, self._artifact(record), options=self._options)

    def _preload_fallback(self, record: EcmVersion) -> None:
        """Load the version that was active before ``record``, if the registry knows one."""
        try:
            detail = self._registry.get_ecm(record.name)
            older = [
                v
                for v in detail.versions
                if v.version != record.version and v.state in (State.SUPERSEDED, State.ACTIVE) and v.kind is record.kind
            ]
            if not older:
                return
            previous = max(older, key=lambda v: (v.version < record.version, v.version))
            self._fallback[record.name] = self._load(previous)
        except CapevoError as exc:
            log.warning("no fallback for %s: %s", _label(record), exc)

    # --- lifetime -----------------------------------------------------------------------

    def close(self) -> None:
        """Release every loaded ECM (kills sandbox workers). Idempotent."""
        if self._closed:
            return
        self._closed = True
        seen: set[int] = set()
        for ecm in [*self._loaded.values(), *self._fallback.values()]:
            if id(ecm) not in seen:
                seen.add(id(ecm))
                try:
                    ecm.close()
                except Exception:  # closing must release the others whatever one does
                    log.exception("closing %s", ecm.label)

    def __enter__(self) -> LoadedCapabilitySet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"LoadedCapabilitySet({self._spec.name!r}, revision={self._revision}, versions={self.versions})"
