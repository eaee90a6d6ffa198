"""Automatic rollback: watch a promoted version's live episodes against its gate evidence.

A version passes the gate on a few held-out seeds; live episodes can still show that it is
worse than the version it replaced. :class:`DegradationMonitor` keeps a sliding window of
the live :class:`EpisodeOutcome` s of each watched (ECM, version) and, once the window holds
at least ``min_episodes``, asks its *signal* whether the live success rate is, with
confidence, below ``reference - margin``. If so it calls
``registry.rollback(name, expected_active=version, reason=...)``, so the audit history says
why, with the numbers.

Reference (``MonitorConfig.reference``):

* ``previous`` (default): the success rate the *replaced* version had on the gate seeds (in
  the promoted version's gate evidence); for a first promotion, the promoted version's own
  lower Wilson bound at the gate.
* ``gate_lower``: the promoted version's lower Wilson bound at the gate.
* ``gate_rate``: the promoted version's success rate at the gate.

Signals (register more with :func:`register_signal`):

* ``wilson_upper``: fire when the upper Wilson bound (one-sided ``1 - alpha``) of the live
  success rate is below the threshold.
* ``binomial``: fire when the exact one-sided binomial test of H0: rate >= threshold has
  p < alpha (``scipy.stats.binomtest(k, n, threshold, alternative="less")``).

What is watched: a version starts being watched when :meth:`DegradationMonitor.on_event`
sees its promotion (register the monitor as a registry listener), when :meth:`watch` is
called, or when :meth:`observe` first meets it as the active version. An outcome counts for
the watched versions in its ``capability_set``; with ``attribution="latest"`` (default) only
for the one whose watch started last (the most recent change is the suspect), with
``"all"`` for each of them.

Confirmation on the same seeds (``replay``): the reference above comes from other seeds than
the live window's, so one hard block of live seeds can fire the signal for a version that is
no worse there than the one it replaced (issue 19's T1 ``il`` run on seed plan 1: the live
block 500100–500109 gave 2/10 to the promoted ``pick.grasp`` v2 *and* to the v1 it replaced).
Given a ``replay`` function, a firing signal is only a screen: the monitor runs the replaced
version on the window's own seeds (each episode's capability set with the watched ECM swapped
back) and asks the signal again with the threshold ``replayed rate - margin``. Only if it
fires again is the version rolled back; otherwise the action is recorded as not confirmed, the
window is emptied and watching goes on. The replay's episodes never count for any watch. A
first promotion (nothing replaced) is judged on the configured reference alone.

Invariants:
1. Nothing is rolled back before the window holds ``min_episodes`` outcomes of the version.
2. Every rollback passes ``expected_active`` = the watched version, so a version that is no
   longer active is never rolled back (the race shows up as an action with ``error`` set).
3. Outcomes of versions that are not active (e.g. a candidate's gate episodes) never count.
4. A version is rolled back at most once per watch; later outcomes of it are ignored.
5. A version with no gate evidence and no ``fallback_reference`` is not monitored.
6. With ``replay``, a version that replaced another is rolled back only when the signal also
   fires against the replaced version's success on the same seeds.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from scipy import stats as sps

from capevo.errors import CapevoError, IllegalTransition, Invalid, NotFound, check_choice
from capevo.records import Action, AuditEvent, EcmVersion, State
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate import EVIDENCE_SCHEMA
from capevo.runtime.gate_stats import check_alpha, wilson_interval

log = logging.getLogger(__name__)

REFERENCES: tuple[str, ...] = ("previous", "gate_lower", "gate_rate")
ATTRIBUTIONS: tuple[str, ...] = ("latest", "all")


# --- signals ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class SignalResult:
    """A signal's verdict on one window."""

    fired: bool
    statistic: float
    """The bound or p-value the signal compared."""
    detail: str


Signal = Callable[[int, int, float, float], SignalResult]
"""``signal(successes, n, threshold, alpha) -> SignalResult``."""

Replay = Callable[[Mapping[str, int], Sequence[int]], Sequence[EpisodeOutcome]]
"""``replay(capability_set, seeds) -> outcomes``: run ``capability_set`` on ``seeds`` (one
outcome per seed), e.g. an :class:`~capevo.runtime.evaluation.Evaluator` bound to the task."""

_SIGNALS: dict[str, Signal] = {}


def register_signal(name: str) -> Callable[[Signal], Signal]:
    """Decorator: make ``fn`` available as signal ``name``."""

    def deco(fn: Signal) -> Signal:
        _SIGNALS[name] = fn
        return fn

    return deco


def make_signal(name: str) -> Signal:
    """The signal registered as ``name``.

    Raises:
        Invalid: unknown name; the message lists the valid ones.
    """
    try:
        return _SIGNALS[name]
    except KeyError:
        raise Invalid(
            f"unknown degradation signal {name!r}; valid: {', '.join(sorted(_SIGNALS))}", details={"field": "signal"}
        ) from None


def signal_names() -> tuple[str, ...]:
    return tuple(sorted(_SIGNALS))


@register_signal("wilson_upper")
def wilson_upper(successes: int, n: int, threshold: float, alpha: float) -> SignalResult:
    """Fire when the one-sided ``1 - alpha`` upper Wilson bound is below ``threshold``."""
    upper = wilson_interval(successes, n, alpha=alpha).high
    return SignalResult(
        fired=upper < threshold,
        statistic=upper,
        detail=f"Wilson upper bound {upper:.3f} ({1 - alpha:.3g} one-sided) vs threshold {threshold:.3f}",
    )


@register_signal("binomial")
def binomial(successes: int, n: int, threshold: float, alpha: float) -> SignalResult:
    """Fire when the exact binomial test of H0: rate >= ``threshold`` has p < ``alpha``."""
    if threshold <= 0.0:
        return SignalResult(fired=False, statistic=1.0, detail=f"threshold {threshold:.3f} <= 0: cannot fire")
    p = float(sps.binomtest(successes, n, min(threshold, 1.0), alternative="less").pvalue)
    return SignalResult(
        fired=p < alpha, statistic=p, detail=f"binomial p={p:.3g} that the rate is below {threshold:.3f}"
    )


# --- configuration and records ----------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class MonitorConfig:
    """When the monitor rolls back.

    Args:
        window: Live outcomes kept per watched version (the most recent).
        min_episodes: Outcomes needed in the window before the signal is asked.
        margin: The threshold is ``reference - margin``.
        alpha: Confidence of the signal.
        signal: A registered signal name (``wilson_upper``, ``binomial``).
        reference: ``previous``, ``gate_lower`` or ``gate_rate`` (module docstring).
        attribution: ``latest`` or ``all`` (module docstring).
        fallback_reference: Reference for versions without gate evidence; None leaves them
            unmonitored.

    Raises:
        Invalid: a value out of range or an unknown name.
    """

    window: int = 50
    min_episodes: int = 20
    margin: float = 0.05
    alpha: float = 0.05
    signal: str = "wilson_upper"
    reference: str = "previous"
    attribution: str = "latest"
    fallback_reference: float | None = None

    def __post_init__(self) -> None:
        for name, low in (("window", 1), ("min_episodes", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise Invalid(f"{name} must be an integer >= {low}, got {v!r}", details={"field": name})
        if self.min_episodes > self.window:
            raise Invalid(
                f"min_episodes ({self.min_episodes}) cannot exceed window ({self.window})",
                details={"field": "min_episodes"},
            )
        for name in ("margin",) + (("fallback_reference",) if self.fallback_reference is not None else ()):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise Invalid(f"{name} must be a number in [0, 1], got {v!r}", details={"field": name})
        check_alpha(self.alpha)
        make_signal(self.signal)
        check_choice(self.reference, REFERENCES, what="reference", field="reference")
        check_choice(self.attribution, ATTRIBUTIONS, what="attribution", field="attribution")

    @classmethod
    def cpu_small(cls) -> MonitorConfig:
        """Tiny live budgets: judge after 8 episodes, window 20, margin 10 points."""
        return cls(window=20, min_episodes=8, margin=0.1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "window": self.window,
            "min_episodes": self.min_episodes,
            "margin": self.margin,
            "alpha": self.alpha,
            "signal": self.signal,
            "reference": self.reference,
            "attribution": self.attribution,
            "fallback_reference": self.fallback_reference,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Reference:
    """The success rate a watched version must not fall below (minus the margin), and why."""

    value: float
    source: str
    """Human-readable origin, e.g. ``v2's success at gate (7/10)``."""


@dataclass(frozen=True, slots=True, kw_only=True)
class MonitorAction:
    """What the monitor did when a watched version's signal fired."""

    name: str
    version: int
    rolled_back: bool
    to_version: int | None
    """The version active after the rollback; None when it failed."""
    n: int
    successes: int
    live_rate: float
    statistic: float
    reference: float
    threshold: float
    signal: str
    reason: str
    error: str | None = None
    at: float = 0.0
    replayed: Mapping[str, Any] | None = None
    """The confirmation on the window's seeds: ``version`` (the replaced one), ``n``,
    ``successes``, ``steps`` (env steps it spent), ``statistic``, ``threshold`` and
    ``confirmed``; None when there was no replay."""

    @property
    def confirmed(self) -> bool:
        """The signal fired and, where the replaced version was replayed, fired again."""
        return self.replayed is None or bool(self.replayed.get("confirmed"))

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "version": self.version,
            "rolled_back": self.rolled_back,
            "to_version": self.to_version,
            "n": self.n,
            "successes": self.successes,
            "live_rate": self.live_rate,
            "statistic": self.statistic,
            "reference": self.reference,
            "threshold": self.threshold,
            "signal": self.signal,
            "reason": self.reason,
            "error": self.error,
            "at": self.at,
            "replayed": dict(self.replayed) if self.replayed is not None else None,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class WatchStatus:
    """One watched version as the monitor sees it now."""

    name: str
    version: int
    state: str
    """``watching``, ``unmonitored`` (no reference), ``rolling_back`` (confirming or rolling
    back), ``rolled_back`` or ``stopped`` (superseded by a newer watch of the same ECM, or its
    rollback failed)."""
    reference: Reference | None
    n: int
    successes: int


@runtime_checkable
class MonitorRegistry(Protocol):
    """What the monitor needs of a registry."""

    def get_version(self, name: str, version: int | None = None) -> EcmVersion: ...

    def rollback(
        self,
        name: str,
        to: int | None = None,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion: ...


def _promotion_evidence(record: EcmVersion) -> Mapping[str, Any] | None:
    """``record``'s gate evidence if it is a promotion the monitor can read, else None."""
    ev = record.gate_evidence
    if isinstance(ev, Mapping) and ev.get("schema") == EVIDENCE_SCHEMA and ev.get("decision") == "promote":
        return ev
    return None


def reference_of(record: EcmVersion, config: MonitorConfig) -> Reference | None:
    """The reference success rate of ``record`` from its gate evidence, or the fallback.

    Returns:
        None when the version has no usable gate evidence and no fallback is configured.
    """
    ev = _promotion_evidence(record)
    if ev is None:
        if config.fallback_reference is None:
            return None
        return Reference(value=float(config.fallback_reference), source="configured fallback (no gate evidence)")
    cand = ev["candidate"]
    own_lower = Reference(
        value=float(cand["success_interval"]["low"]),
        source=f"v{record.version}'s lower bound at gate ({cand['successes']}/{cand['n']})",
    )
    if config.reference == "gate_lower":
        return own_lower
    if config.reference == "gate_rate":
        return Reference(
            value=float(cand["success_rate"]),
            source=f"v{record.version}'s success at gate ({cand['successes']}/{cand['n']})",
        )
    prev = ev.get("active")
    if not prev:
        return own_lower
    return Reference(
        value=float(prev["success_rate"]),
        source=f"v{ev.get('active_version')}'s success at gate ({prev['successes']}/{prev['n']}, replaced)",
    )


def replaced_version(record: EcmVersion) -> int | None:
    """The version ``record``'s promotion replaced, from its gate evidence (None: a first promotion)."""
    ev = _promotion_evidence(record)
    if ev is None or not ev.get("active") or ev.get("active_version") is None:
        return None
    return int(ev["active_version"])


@dataclass(frozen=True, slots=True)
class _Seen:
    """One live episode in a watch's window."""

    seed: int
    success: bool
    capability_set: tuple[tuple[str, int], ...]


class _Watch:
    __slots__ = ("name", "reference", "replaced", "seq", "state", "version", "window")

    def __init__(
        self, name: str, version: int, reference: Reference | None, replaced: int | None, seq: int, window: int
    ) -> None:
        self.name = name
        self.version = version
        self.reference = reference
        self.replaced = replaced
        self.seq = seq
        self.state = "watching" if reference is not None else "unmonitored"
        self.window: deque[_Seen] = deque(maxlen=window)

    @property
    def successes(self) -> int:
        return sum(e.success for e in self.window)


class DegradationMonitor:
    """Rolls back a promoted version whose live success falls below its gate evidence.

    Args:
        registry: Where versions are read and rollbacks go.
        config: Window, threshold and signal.
        actor: Audit actor of rollbacks.
        on_action: Called with every :class:`MonitorAction` (e.g. to log or alert).
        replay: Runs a capability set on seeds; given, a firing signal is confirmed against the
            replaced version on the window's own seeds before any rollback (module docstring).

    Raises:
        Invalid: ``config`` is not a :class:`MonitorConfig`.
    """

    def __init__(
        self,
        registry: MonitorRegistry,
        *,
        config: MonitorConfig | None = None,
        actor: str = "monitor",
        on_action: Callable[[MonitorAction], object] | None = None,
        replay: Replay | None = None,
    ) -> None:
        if config is not None and not isinstance(config, MonitorConfig):
            raise Invalid(f"config must be a MonitorConfig, got {type(config).__name__}", details={"field": "config"})
        self.registry = registry
        self.config = config if config is not None else MonitorConfig()
        self.actor = actor
        self.on_action = on_action
        self.replay = replay
        self._signal = make_signal(self.config.signal)
        self._watches: dict[tuple[str, int], _Watch] = {}
        self._seq = itertools.count()
        self._lock = threading.RLock()
        self.actions: list[MonitorAction] = []

    # --- what is watched ----------------------------------------------------------------

    def watch(self, name: str, version: int | None = None) -> WatchStatus:
        """Start (or restart, with an empty window) watching ``version`` (default: the active one).

        Raises:
            NotFound: no such ECM/version, or none active. Invalid: bad name or version.
            IllegalTransition: ``version`` is not the active version (only it runs live).
        """
        record = self.registry.get_version(name, version)
        if record.state is not State.ACTIVE:
            raise IllegalTransition(
                f"{name} v{record.version} is {record.state.value}; only the active version can be watched",
                details={"name": name, "version": record.version, "state": record.state.value},
            )
        with self._lock:
            self._start(record)
            return self._status(self._watches[(record.name, record.version)])

    def _start(self, record: EcmVersion) -> _Watch:
        w = _Watch(
            record.name,
            record.version,
            reference_of(record, self.config),
            replaced_version(record),
            next(self._seq),
            self.config.window,
        )
        for (n, _), other in self._watches.items():
            if n == record.name and other.state == "watching":
                other.state = "stopped"
        self._watches[(record.name, record.version)] = w
        if w.reference is None:
            log.info("monitor: %s v%d has no gate evidence; not monitored", record.name, record.version)
        return w

    def on_event(self, event: AuditEvent, record: EcmVersion) -> None:
        """Registry listener: watch each newly promoted version; forget a rolled-back one.

        A rollback re-activates an older version; it is watched afresh only if it has
        gate evidence (or a fallback reference).
        """
        if event.action in (Action.PROMOTE, Action.ROLLBACK) and record.state is State.ACTIVE:
            with self._lock:
                self._start(record)

    def status(self) -> list[WatchStatus]:
        """Every version the monitor knows of, oldest watch first."""
        with self._lock:
            return [self._status(w) for w in sorted(self._watches.values(), key=lambda w: w.seq)]

    @staticmethod
    def _status(w: _Watch) -> WatchStatus:
        return WatchStatus(
            name=w.name,
            version=w.version,
            state=w.state,
            reference=w.reference,
            n=len(w.window),
            successes=w.successes,
        )

    # --- feeding ------------------------------------------------------------------------

    def observe(self, outcome: EpisodeOutcome) -> list[MonitorAction]:
        """Count one live episode for the watched versions it ran; roll back where the signal fires.

        Returns:
            The actions taken because of this outcome (usually none).

        Raises:
            Invalid: ``outcome`` is not an :class:`EpisodeOutcome`.
        """
        if not isinstance(outcome, EpisodeOutcome):
            raise Invalid(f"observe takes an EpisodeOutcome, got {type(outcome).__name__}")
        ran = sorted((str(n), int(v)) for n, v in outcome.capability_set.items())
        with self._lock:
            unknown = [key for key in ran if key not in self._watches]
        # Registry calls happen outside the lock: a registry calls its listeners (our
        # on_event) under its own lock, so holding ours across a call could deadlock.
        found = [r for r in (self._active_record(n, v) for n, v in unknown) if r is not None]
        with self._lock:
            for record in found:
                if (record.name, record.version) not in self._watches:
                    self._start(record)
            targets = [w for key in ran if (w := self._watches.get(key)) is not None and w.state == "watching"]
            if self.config.attribution == "latest" and targets:
                targets = [max(targets, key=lambda w: w.seq)]
            firing = []
            seen = _Seen(int(outcome.seed), bool(outcome.success), tuple(ran))
            for w in targets:
                w.window.append(seen)
                verdict = self._verdict(w)
                if verdict is not None and w.reference is not None:
                    w.state = "rolling_back"
                    firing.append((w, w.reference, tuple(w.window), verdict))
        actions = [self._act(w, ref, window, verdict) for w, ref, window, verdict in firing]
        for a in actions:
            if self.on_action is not None:
                self.on_action(a)
        return actions

    def observe_many(self, outcomes: Sequence[EpisodeOutcome]) -> list[MonitorAction]:
        """:meth:`observe` each outcome in order; all actions taken."""
        out: list[MonitorAction] = []
        for o in outcomes:
            out.extend(self.observe(o))
        return out

    def _active_record(self, name: str, version: int) -> EcmVersion | None:
        # Only the active version is watched: a candidate's gate episodes must not count.
        try:
            active = self.registry.get_version(name)
        except NotFound:
            return None
        return active if active.version == version else None

    def _verdict(self, w: _Watch) -> SignalResult | None:
        cfg = self.config
        n = len(w.window)
        if n < cfg.min_episodes or w.reference is None:
            return None
        verdict = self._signal(w.successes, n, w.reference.value - cfg.margin, cfg.alpha)
        return verdict if verdict.fired else None

    def _replay(self, w: _Watch, window: Sequence[_Seen]) -> tuple[int, int]:
        """(successes, env steps) of ``w.replaced`` on the window's seeds, each episode's set otherwise kept."""
        assert self.replay is not None and w.replaced is not None
        by_set: dict[tuple[tuple[str, int], ...], list[int]] = {}
        for e in window:
            swapped = tuple((n, w.replaced if n == w.name else v) for n, v in e.capability_set)
            by_set.setdefault(swapped, []).append(e.seed)
        successes = steps = 0
        for caps, seeds in by_set.items():
            outcomes = list(self.replay(dict(caps), seeds))
            if sorted(int(o.seed) for o in outcomes) != sorted(seeds):
                raise Invalid(
                    f"replay of {w.name} v{w.replaced} returned seeds {[o.seed for o in outcomes]}, asked {seeds}",
                    details={"field": "replay"},
                )
            successes += sum(bool(o.success) for o in outcomes)
            steps += sum(int(o.steps) for o in outcomes)
        return successes, steps

    def _act(self, w: _Watch, ref: Reference, window: Sequence[_Seen], verdict: SignalResult) -> MonitorAction:
        """Confirm a firing signal on the same seeds where possible, then roll back or go on watching."""
        if self.replay is None or w.replaced is None:
            return self._roll_back(w, ref, window, verdict)
        cfg = self.config
        n, k = len(window), sum(e.success for e in window)
        try:
            k_old, steps = self._replay(w, window)
        except BaseException:
            with self._lock:
                w.state = "watching"  # the window stays: the next outcome asks again
            raise
        paired = Reference(
            value=k_old / n, source=f"v{w.replaced} replayed on the same {n} seeds ({k_old}/{n}, replaced)"
        )
        second = self._signal(k, n, paired.value - cfg.margin, cfg.alpha)
        replayed = {
            "version": w.replaced,
            "n": n,
            "successes": k_old,
            "steps": steps,
            "statistic": second.statistic,
            "threshold": paired.value - cfg.margin,
            "confirmed": second.fired,
        }
        if second.fired:
            confirmed = f"; confirmed against {paired.source}: {second.detail}"
            return self._roll_back(w, ref, window, verdict, confirmed=confirmed, replayed=replayed)
        reason = (
            f"monitor: keep {w.name} v{w.version}: live success {k}/{n} = {k / n:.2f} fired the screen "
            f"({verdict.detail}; reference {ref.value:.3f} [{ref.source}] - margin {cfg.margin:.3f}), "
            f"but not against {paired.source}: {second.detail}; window emptied"
        )
        log.info("%s", reason)
        action = self._action(w, ref, window, verdict, reason=reason, replayed=replayed)
        with self._lock:
            if w.state == "rolling_back":
                w.state = "watching"
                w.window.clear()
            self.actions.append(action)
        return action

    def _action(
        self,
        w: _Watch,
        ref: Reference,
        window: Sequence[_Seen],
        verdict: SignalResult,
        *,
        reason: str,
        to_version: int | None = None,
        error: str | None = None,
        replayed: Mapping[str, Any] | None = None,
    ) -> MonitorAction:
        n, k = len(window), sum(e.success for e in window)
        return MonitorAction(
            name=w.name,
            version=w.version,
            rolled_back=to_version is not None,
            to_version=to_version,
            n=n,
            successes=k,
            live_rate=k / n,
            statistic=verdict.statistic,
            reference=ref.value,
            threshold=ref.value - self.config.margin,
            signal=self.config.signal,
            reason=reason,
            error=error,
            at=time.time(),
            replayed=replayed,
        )

    def _roll_back(
        self,
        w: _Watch,
        ref: Reference,
        window: Sequence[_Seen],
        verdict: SignalResult,
        *,
        confirmed: str = "",
        replayed: Mapping[str, Any] | None = None,
    ) -> MonitorAction:
        cfg = self.config
        n, k = len(window), sum(e.success for e in window)
        reason = (
            f"monitor: roll back {w.name} v{w.version}: live success {k}/{n} = {k / n:.2f} over the last "
            f"{n} episodes; {verdict.detail}; threshold = reference {ref.value:.3f} "
            f"[{ref.source}] - margin {cfg.margin:.3f} (signal {cfg.signal}, alpha {cfg.alpha:.3g}){confirmed}"
        )
        to_version: int | None = None
        error: str | None = None
        try:
            after = self.registry.rollback(w.name, expected_active=w.version, reason=reason, actor=self.actor)
            to_version = after.version
            log.warning("%s -> v%d", reason, to_version)
        except CapevoError as exc:
            # Lost a race (Conflict), nothing to go back to (NotFound), or the registry is
            # unreachable: report it; the watch stops so it does not retry every episode.
            error = str(exc)
            log.error("%s: rollback failed: %s", reason, exc)
        action = self._action(
            w,
            ref,
            window,
            verdict,
            reason=reason,
            to_version=to_version,
            error=error,
            replayed=replayed,
        )
        with self._lock:
            w.state = "rolled_back" if action.rolled_back else "stopped"
            self.actions.append(action)
        return action


__all__ = [
    "ATTRIBUTIONS",
    "REFERENCES",
    "DegradationMonitor",
    "MonitorAction",
    "MonitorConfig",
    "MonitorRegistry",
    "Reference",
    "Replay",
    "SignalResult",
    "WatchStatus",
    "binomial",
    "make_signal",
    "reference_of",
    "register_signal",
    "replaced_version",
    "signal_names",
    "wilson_upper",
]
