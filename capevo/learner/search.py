"""Offline parameter search: the cross-entropy method (CEM) over one code ECM's ``PARAMS``.

Given a :class:`~capevo.learner.base.LearnRequest`, :class:`CemSearch` keeps the ECM's code
and searches its numeric parameters θ: each iteration samples a population of θ from a
diagonal Gaussian, runs every candidate (unpublished, through a
:class:`~capevo.learner.base.CandidateEvaluator`) on the same few training seeds with the
task's other ECMs at their versions (or, for the request's *companions*, the unpublished
candidates learned before it in the same update), ranks them (safety: the fraction of
episodes where governance stopped a step of the tuned ECM; then success rate; then the fraction
of episodes that got past the tuned ECM; then progress through the decomposition; then speed,
fewer steps spent in the tuned ECM, since a slow step leaves later steps short of the horizon;
then reward per step), and refits the Gaussian (smoothed) to the elite fraction. It stops
early, after ``min_iterations``, once the best candidate gets every episode past the ECM. The last iteration's
best few are then validated on fresh training seeds and the best on all their episodes wins.
The candidate is the parent's source (or the request's starting source) with only the
``PARAMS`` literal rewritten (:func:`~capevo.runtime.ecm.code.with_params`); its own episodes
are kept as the candidate's ``experience`` (where they still fail says what to learn next).

Search space: a parameter the skill gives a plausible span in its ``PARAM_RANGES`` literal
(``{name: (low, high)}``, or ``(low, high, "log")`` for gains and other positive factors,
written by hand with the skill, read here without running it) is searched within that span in
units of a quarter of its width (of its log width on a log scale). Any other parameter is searched
in units of its *scale*, ``max(|v0|, floor)`` (v0 its value in the parent), within
``v0 ± spread · scale``; a parameter whose parent value is positive stays ≥ 0 and a negative
one ≤ 0 (gains, heights and widths keep their sign). Explicit ``bounds`` override both (the
scale then stays the automatic one).

Tied ECMs (``LearnRequest.tied``; ``capevo evolve --tie-siblings``): other ECMs of the same
skill, T5's same step for the other two objects. Every evaluation writes the sampled θ into
them too, so one search finds one parameter set for the step wherever it runs, with the episodes
of all its objects as evidence; the hand-set row shares one set the same way. What is shared is
the hand-written template; each object keeps its own placeholders (grasp height, ridge).

Which ECM: :func:`~capevo.learner.experience.pick_ecm_to_update` reads recent traces and
names the step that failed episodes blame most: the steps that did not hand over to a later
one (exported here too).

Origin: a CEM candidate is published as ``clone`` by default: its artifact is a copy of the
parent's code with new parameter values, not new code (``rl`` would claim a trained policy,
``hybrid`` is reserved for LLM edit + search). ``origin=`` changes it.

Invariants:
1. Every evaluated θ lies within the bounds; the parent's θ is the first candidate of the
   first iteration (so ``baseline`` is the parent on the same seeds).
2. Within one iteration every candidate runs on the same seeds; iterations use successive
   slices of the training seeds (cycling).
3. With equal configuration, request and evaluator behaviour, the search is deterministic.
4. The returned source differs from the parent's only inside the ``PARAMS`` literal.
5. The returned θ is one of the last iteration's ``validate_top`` best (its best when
   validation is off).
6. With ``max_env_steps`` set, the search's episodes take at most that many env steps in all
   (``CemResult.env_steps_run``); the first iteration runs as many candidates as fit (at least
   the parent's θ, or :class:`Invalid`), a later one runs whole or not at all.
7. Every evaluation runs each tied ECM with exactly the evaluated θ, and each tied candidate's
   ``PARAMS`` equal the returned θ.
"""

from __future__ import annotations

import ast
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.learner.base import Candidate, CandidateEvaluator, LearnRequest, Score, config_hash, score_outcomes
from capevo.learner.experience import EpisodeEnd, episode_ends, handover_rate, pick_ecm_to_update, trace_paths
from capevo.records import EcmVersion, Origin, Provenance, PublishSpec
from capevo.runtime.ecm.code import read_params, with_params

log = logging.getLogger(__name__)

__all__ = [
    "CEM_PRESETS",
    "CemConfig",
    "CemEvent",
    "CemResult",
    "CemSearch",
    "ParamRange",
    "ParamSpace",
    "cem_preset",
    "param_space",
    "pick_ecm_to_update",
    "read_ranges",
]


def _bad(name: str, message: str) -> Invalid:
    return Invalid(f"{name}: {message}", details={"field": name})


@dataclass(frozen=True, slots=True, kw_only=True)
class CemConfig:
    """Settings of one CEM search (hashed into the candidate's provenance).

    Args:
        population: Candidates per iteration (the first is the current mean).
        elite_frac: Fraction of the population the Gaussian is refitted to (at least one).
        iterations: Iterations at most.
        episodes_per_candidate: Training episodes per candidate.
        seed: Seeds the sampler.
        sigma_init: Initial standard deviation, in units of each parameter's scale.
        sigma_min: Floor of the standard deviation after refitting (keeps exploring).
        spread: Half-width of the search box, in units of each parameter's scale.
        floor: Smallest scale (a parameter at 0 is searched in ``± spread · floor``).
        keys: Parameters to search (default all); the others keep the parent's values.
        bounds: ``(name, low, high)`` triples overriding the automatic box.
        stop_when_passed: Stop after an iteration whose best candidate got every episode
            past the ECM (it no longer is where episodes end).
        min_iterations: Iterations run before ``stop_when_passed`` may stop the search.
        smoothing: Weight of the elites when refitting (1 = plain CEM); the rest keeps the
            previous mean and standard deviation.
        validate_top: How many of the last iteration's best candidates are validated.
        validation_episodes: Extra episodes (on training seeds after the iterations' ones)
            for each of them; the candidate is the best on all its episodes. 0 skips this.
        max_env_steps: Env steps the whole search (iterations and validation) may spend; None
            for no cap. A candidate whose episodes could take it past the cap (each episode
            counted at ``episode_steps_max``, the horizon) is not run: the search stops there
            and returns the best candidate evaluated (issue 20: budget parity).
        episode_steps_max: Most env steps one episode can take (the horizon); needed with
            ``max_env_steps``.

    Raises:
        Invalid: a value out of range, or a cap without ``episode_steps_max``.
    """

    population: int = 8
    elite_frac: float = 0.25
    iterations: int = 3
    episodes_per_candidate: int = 4
    seed: int = 0
    sigma_init: float = 1.0
    sigma_min: float = 0.05
    spread: float = 3.0
    floor: float = 0.01
    keys: tuple[str, ...] | None = None
    bounds: tuple[tuple[str, float, float], ...] = ()
    stop_when_passed: bool = True
    min_iterations: int = 1
    smoothing: float = 0.7
    validate_top: int = 2
    validation_episodes: int = 0
    max_env_steps: int | None = None
    episode_steps_max: int | None = None

    def __post_init__(self) -> None:
        for name in ("max_env_steps", "episode_steps_max"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise _bad(name, f"must be a positive integer or None, got {v!r}")
        if self.max_env_steps is not None and self.episode_steps_max is None:
            raise _bad("episode_steps_max", "is needed with max_env_steps (the most steps one episode can take)")
        ints = {
            "population": (self.population, 2, 10_000),
            "iterations": (self.iterations, 1, 10_000),
            "episodes_per_candidate": (self.episodes_per_candidate, 1, 10_000),
            "min_iterations": (self.min_iterations, 1, 10_000),
            "validate_top": (self.validate_top, 1, 10_000),
            "validation_episodes": (self.validation_episodes, 0, 10_000),
        }
        for name, (v, lo, hi) in ints.items():
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise _bad(name, f"must be an integer from {lo} to {hi}, got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise _bad("seed", f"must be a non-negative integer, got {self.seed!r}")
        floats = {
            "elite_frac": (self.elite_frac, 0.0, 1.0),
            "sigma_init": (self.sigma_init, 0.0, 100.0),
            "sigma_min": (self.sigma_min, 0.0, 100.0),
            "spread": (self.spread, 0.0, 1000.0),
            "floor": (self.floor, 0.0, 1e6),
            "smoothing": (self.smoothing, 0.0, 1.0),
        }
        for name, (v, lo, hi) in floats.items():
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
            if not ok or not lo < v <= hi:
                raise _bad(name, f"must be a number in ({lo}, {hi}], got {v!r}")
        for name, lo, hi in self.bounds:
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise _bad("bounds", f"{name}: need finite low <= high, got ({lo}, {hi})")

    @property
    def n_elite(self) -> int:
        return max(1, round(self.elite_frac * self.population))

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": "cem",
            "population": self.population,
            "elite_frac": self.elite_frac,
            "iterations": self.iterations,
            "episodes_per_candidate": self.episodes_per_candidate,
            "seed": self.seed,
            "sigma_init": self.sigma_init,
            "sigma_min": self.sigma_min,
            "spread": self.spread,
            "floor": self.floor,
            "keys": list(self.keys) if self.keys is not None else None,
            "bounds": [list(b) for b in self.bounds],
            "stop_when_passed": self.stop_when_passed,
            "min_iterations": self.min_iterations,
            "smoothing": self.smoothing,
            "validate_top": self.validate_top,
            "validation_episodes": self.validation_episodes,
            # only when set: the provenance hashes of uncapped searches stay what they were
            **({"max_env_steps": self.max_env_steps} if self.max_env_steps is not None else {}),
            **({"episode_steps_max": self.episode_steps_max} if self.episode_steps_max is not None else {}),
        }


CEM_PRESETS: Mapping[str, CemConfig] = {
    # tests: a couple of rollouts
    "tiny": CemConfig(population=3, elite_frac=0.34, iterations=1, episodes_per_candidate=1),
    # 2 CPU cores: 8 x 3 episodes per iteration, at most 3 iterations, stop once the ECM passes
    "cpu-small": CemConfig(
        population=8, elite_frac=0.25, iterations=3, episodes_per_candidate=3, validate_top=2, validation_episodes=4
    ),
    # a workstation: wider population, more episodes per estimate
    "paper": CemConfig(
        population=16,
        elite_frac=0.25,
        iterations=6,
        episodes_per_candidate=8,
        min_iterations=2,
        validate_top=3,
        validation_episodes=16,
    ),
}
"""Search budgets by name (the task horizon and per-ECM step budget are the evaluator's)."""


def cem_preset(name: str) -> CemConfig:
    """The :data:`CEM_PRESETS` entry ``name``.

    Raises:
        Invalid: unknown name, listing the valid ones.
    """
    try:
        return CEM_PRESETS[name]
    except KeyError:
        raise Invalid(
            f"unknown CEM preset {name!r}; valid: {', '.join(CEM_PRESETS)}", details={"field": "preset"}
        ) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamSpace:
    """The searched parameters: u = x0 + scale · z, clipped to [low, high]; θ = u, or exp(u)
    for a parameter searched on a log scale (x0, scale, low and high are then in log units)."""

    names: tuple[str, ...]
    x0: tuple[float, ...]
    scale: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    log: tuple[bool, ...] = ()
    """Per parameter: searched on a log scale (empty: none is)."""
    v0: tuple[float, ...] = ()
    """θ at z = 0, exactly (exp(log v) need not round-trip); empty: x0."""

    @property
    def dim(self) -> int:
        return len(self.names)

    def z_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds in normalized units."""
        x0, s = np.array(self.x0), np.array(self.scale)
        return (np.array(self.low) - x0) / s, (np.array(self.high) - x0) / s

    def params(self, z: np.ndarray) -> dict[str, float]:
        """θ for normalized point ``z`` (clipped into the box)."""
        theta = np.clip(np.array(self.x0) + np.array(self.scale) * np.asarray(z, dtype=np.float64), self.low, self.high)
        if any(self.log):
            theta = np.where(np.array(self.log), np.exp(theta), theta)
            if self.v0:
                theta = np.where(np.asarray(z, dtype=np.float64) == 0.0, np.array(self.v0), theta)
        return {n: float(v) for n, v in zip(self.names, theta.tolist(), strict=True)}


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamRange:
    """A span a skill declares plausible for one parameter (``PARAM_RANGES``)."""

    low: float
    high: float
    log: bool = False
    """Search on a log scale (gains and other positive factors: doubling matters, not +1)."""


RANGE_UNITS = 4.0
"""A declared range is searched in units of its width / RANGE_UNITS."""
RANGES_NAME = "PARAM_RANGES"


def read_ranges(source: str, *, filename: str = "<skill>") -> dict[str, ParamRange]:
    """The skill's ``PARAM_RANGES`` literal, read without running it.

    Each entry is ``name: (low, high)`` or ``name: (low, high, "log")`` (searched on a log
    scale; needs 0 < low).

    Returns:
        The ranges; empty when the skill declares none.

    Raises:
        Invalid: not valid Python, or ``PARAM_RANGES`` is not such a literal dict of finite
            bounds with low < high.
    """
    try:
        tree = ast.parse(source, filename=filename)
    except SyntaxError as exc:
        raise Invalid(f"{filename}: not valid Python: {exc.msg} (line {exc.lineno})") from None
    node = next(
        (
            n
            for n in tree.body
            if isinstance(n, ast.Assign) and any(isinstance(t, ast.Name) and t.id == RANGES_NAME for t in n.targets)
        ),
        None,
    )
    if node is None:
        return {}
    try:
        value = ast.literal_eval(node.value)
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError) as exc:
        raise Invalid(f"{filename}: line {node.lineno}: {RANGES_NAME} must be a literal dict: {exc}") from None
    out: dict[str, ParamRange] = {}
    ok = isinstance(value, dict)
    for k, v in value.items() if ok else ():
        entry = tuple(v) if isinstance(v, (tuple, list)) else ()
        pair, flag = entry[:2], entry[2:]
        log = flag == ("log",)
        if (
            not isinstance(k, str)
            or len(pair) != 2
            or flag not in ((), ("log",))
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in pair)
            or not pair[0] < pair[1]
            or (log and pair[0] <= 0)
        ):
            ok = False
            break
        out[k] = ParamRange(low=float(pair[0]), high=float(pair[1]), log=log)
    if not ok:
        raise Invalid(
            f"{filename}: line {node.lineno}: {RANGES_NAME} must map names to finite (low, high) or "
            '(low, high, "log") with low < high (and 0 < low on a log scale)',
            details={"field": RANGES_NAME},
        )
    return out


def param_space(
    params: Mapping[str, float],
    *,
    spread: float = 3.0,
    floor: float = 0.01,
    keys: Sequence[str] | None = None,
    bounds: Sequence[tuple[str, float, float]] = (),
    ranges: Mapping[str, ParamRange] | None = None,
) -> ParamSpace:
    """The search box around ``params`` (see the module docstring).

    Raises:
        Invalid: ``keys`` or ``bounds`` name a parameter ``params`` lacks, or nothing to search.
    """
    names = tuple(keys) if keys is not None else tuple(params)
    unknown = sorted(set(names) - set(params)) + sorted({b[0] for b in bounds} - set(params))
    if unknown:
        raise Invalid(
            f"unknown parameter(s) {unknown}; the skill's PARAMS declares {sorted(params)}", details={"field": "keys"}
        )
    if not names:
        raise Invalid("nothing to search: the skill declares no PARAMS (or keys is empty)", details={"field": "keys"})
    explicit = {b[0]: (float(b[1]), float(b[2])) for b in bounds}
    declared = dict(ranges or {})
    x0, scale, low, high, log, v0 = [], [], [], [], [], []
    for n in names:
        v = float(params[n])
        s = max(abs(v), floor)
        lo, hi = v - spread * s, v + spread * s
        on_log = False
        if v > 0:
            lo = max(lo, 0.0)
        elif v < 0:
            hi = min(hi, 0.0)
        if n in explicit:
            lo, hi = explicit[n]
            v = min(max(v, lo), hi)
        elif n in declared:
            r = declared[n]
            lo, hi, on_log = r.low, r.high, r.log
            v = min(max(v, lo), hi)
            if on_log:
                v0.append(v)
                lo, hi, v = math.log(lo), math.log(hi), math.log(v)
            s = (hi - lo) / RANGE_UNITS
        x0.append(v)
        scale.append(s)
        low.append(lo)
        high.append(hi)
        log.append(on_log)
        if not on_log:
            v0.append(v)
    return ParamSpace(
        names=names, x0=tuple(x0), scale=tuple(scale), low=tuple(low), high=tuple(high), log=tuple(log), v0=tuple(v0)
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class CemEvent:
    """One evaluated candidate, passed to the progress callback."""

    iteration: int
    index: int
    params: Mapping[str, float]
    score: Score
    seeds: tuple[int, ...]
    passed: float
    """Fraction of its episodes that got past the ECM being tuned."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration,
            "index": self.index,
            "params": dict(self.params),
            "score": self.score.to_dict(),
            "seeds": list(self.seeds),
            "passed": self.passed,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class CemResult:
    """What a search found."""

    params: Mapping[str, float]
    """Full θ of the best candidate (searched and kept parameters)."""
    source: str
    score: Score
    baseline: Score
    """The parent's θ, first candidate of the first iteration."""
    iterations_run: int
    episodes_run: int
    env_steps_run: int = 0
    """Env steps of every episode the search ran (≤ ``max_env_steps`` when capped)."""
    stopped_by_budget: bool = False
    """The step cap ended the search before its iterations (or validation) were done."""
    history: tuple[CemEvent, ...] = field(default_factory=tuple)
    experience: tuple[Any, ...] = ()
    """The best candidate's own episodes (iteration and validation), with their traces."""
    tied_sources: Mapping[str, str] = field(default_factory=dict)
    """The request's tied ECMs' sources with the best θ written in, by ECM name."""


@dataclass(slots=True)
class _Finalist:
    index: int
    theta: dict[str, float]
    source: str
    outcomes: list[Any]
    ends: list[EpisodeEnd]
    score: Score
    passed: float

    steps: float = 0.0
    """Mean environment steps per episode spent in the tuned ECM."""
    unsafe: float = 0.0
    """Fraction of episodes where the safety monitor graded a step of the tuned ECM unsafe."""

    def rank(self) -> tuple[float, float, float, float, float, float]:
        """Safety first (the gate rejects a version that is unsafe more often), then success,
        then how often the tuned ECM handed over, then progress, then speed (fewer steps in the
        tuned ECM: what it spends, later steps lack before the horizon; only among candidates
        that handed over at all, a step that gives up early is not fast), then reward."""
        s = self.score
        speed = -self.steps if self.passed > 0 else 0.0
        return (-self.unsafe, s.success_rate, self.passed, s.progress, speed, s.reward_per_step)


def _validation_seeds(seeds: Sequence[int], cfg: CemConfig) -> tuple[int, ...]:
    """The training seeds after the iterations' slices (cycling), for validating finalists."""
    start = cfg.iterations * cfg.episodes_per_candidate
    return tuple(seeds[(start + j) % len(seeds)] for j in range(cfg.validation_episodes))


def _seed_slices(seeds: Sequence[int], per: int, count: int) -> list[tuple[int, ...]]:
    if not seeds:
        raise Invalid("the request has no training seeds", details={"field": "train_seeds"})
    out = []
    for i in range(count):
        out.append(tuple(seeds[(i * per + j) % len(seeds)] for j in range(per)))
    return out


class CemSearch:
    """CEM over one code ECM's parameters (see the module docstring).

    Args:
        evaluator: Runs unpublished candidates (e.g. a
            :class:`~capevo.learner.scratch.ScratchRegistryEvaluator`).
        population, elite_frac, iterations, episodes_per_candidate, seed, sigma_init,
        sigma_min, spread, floor, keys, bounds, stop_when_passed, min_iterations, smoothing,
        validate_top, validation_episodes: see
            :class:`CemConfig`.
        origin: Origin of the candidate it returns (and of the artifacts it evaluates, so
            they run under the same trust); default ``clone``.
        learner_id: Recorded in provenance.
        progress: Called with a :class:`CemEvent` after every candidate.

    Raises:
        Invalid: a bad setting.
    """

    def __init__(
        self,
        evaluator: CandidateEvaluator,
        *,
        population: int = 8,
        elite_frac: float = 0.25,
        iterations: int = 3,
        episodes_per_candidate: int = 4,
        seed: int = 0,
        sigma_init: float = 1.0,
        sigma_min: float = 0.05,
        spread: float = 3.0,
        floor: float = 0.01,
        keys: Sequence[str] | None = None,
        bounds: Mapping[str, tuple[float, float]] | None = None,
        stop_when_passed: bool = True,
        min_iterations: int = 1,
        smoothing: float = 0.7,
        validate_top: int = 2,
        validation_episodes: int = 0,
        max_env_steps: int | None = None,
        episode_steps_max: int | None = None,
        origin: Origin = Origin.CLONE,
        learner_id: str = "cem",
        progress: Callable[[CemEvent], Any] | None = None,
    ) -> None:
        self.config = CemConfig(
            population=population,
            elite_frac=elite_frac,
            iterations=iterations,
            episodes_per_candidate=episodes_per_candidate,
            seed=seed,
            sigma_init=sigma_init,
            sigma_min=sigma_min,
            spread=spread,
            floor=floor,
            keys=tuple(keys) if keys is not None else None,
            bounds=tuple((k, float(lo), float(hi)) for k, (lo, hi) in sorted((bounds or {}).items())),
            stop_when_passed=stop_when_passed,
            min_iterations=min_iterations,
            smoothing=smoothing,
            validate_top=validate_top,
            validation_episodes=validation_episodes,
            max_env_steps=max_env_steps,
            episode_steps_max=episode_steps_max,
        )
        self.evaluator = evaluator
        self.origin = Origin(origin)
        self.learner_id = learner_id
        self.progress = progress

    @classmethod
    def from_config(
        cls,
        evaluator: CandidateEvaluator,
        config: CemConfig,
        *,
        origin: Origin = Origin.CLONE,
        learner_id: str = "cem",
        progress: Callable[[CemEvent], Any] | None = None,
    ) -> CemSearch:
        """A search with ``config`` (e.g. ``cem_preset("cpu-small")``)."""
        return cls(
            evaluator,
            population=config.population,
            elite_frac=config.elite_frac,
            iterations=config.iterations,
            episodes_per_candidate=config.episodes_per_candidate,
            seed=config.seed,
            sigma_init=config.sigma_init,
            sigma_min=config.sigma_min,
            spread=config.spread,
            floor=config.floor,
            keys=config.keys,
            bounds={name: (lo, hi) for name, lo, hi in config.bounds},
            stop_when_passed=config.stop_when_passed,
            min_iterations=config.min_iterations,
            smoothing=config.smoothing,
            validate_top=config.validate_top,
            validation_episodes=config.validation_episodes,
            max_env_steps=config.max_env_steps,
            episode_steps_max=config.episode_steps_max,
            origin=origin,
            learner_id=learner_id,
            progress=progress,
        )

    # --- the search ------------------------------------------------------------------

    def search(
        self, request: LearnRequest, *, source: str | None = None, evaluation_origin: Origin | None = None
    ) -> CemResult:
        """Run CEM on ``request.ecm``, starting from ``source`` (default the parent's).

        ``evaluation_origin`` (default :attr:`origin`) is the origin the samples run under,
        which decides their trust (``hybrid`` for LLM-edited code).

        Raises:
            Invalid: no training seeds, no ``PARAMS`` to search, or bad keys/bounds.
            CapevoError: whatever the evaluator raised.
        """
        cfg = self.config
        src = source if source is not None else request.source
        start = read_params(src, filename=f"<{request.ecm}>")
        space = param_space(
            start,
            spread=cfg.spread,
            floor=cfg.floor,
            keys=cfg.keys,
            bounds=cfg.bounds,
            ranges={k: r for k, r in read_ranges(src, filename=f"<{request.ecm}>").items() if k in start},
        )
        tied_start = _tied_params(request, start)
        zlo, zhi = space.z_bounds()
        rng = np.random.default_rng(cfg.seed)
        mean = np.clip(np.zeros(space.dim), zlo, zhi)
        sigma = np.full(space.dim, cfg.sigma_init)
        slices = _seed_slices(request.train_seeds, cfg.episodes_per_candidate, cfg.iterations)
        decomposition = request.decomposition
        ecm_index = decomposition.index(request.ecm) if request.ecm in decomposition else -1
        history: list[CemEvent] = []
        baseline: Score | None = None
        finalists: list[_Finalist] = []
        episodes = 0
        env_steps = 0
        iterations_run = 0
        stopped_by_budget = False

        def affordable(n_episodes: int) -> bool:
            # the worst case (every episode to the horizon) must fit under the cap
            if cfg.max_env_steps is None or cfg.episode_steps_max is None:
                return True
            return env_steps + n_episodes * cfg.episode_steps_max <= cfg.max_env_steps

        if not affordable(len(slices[0])):
            raise Invalid(
                f"a step cap of {cfg.max_env_steps} env steps cannot cover one candidate "
                f"({len(slices[0])} episodes of up to {cfg.episode_steps_max} steps)",
                details={"field": "max_env_steps"},
            )

        def tied_sources(theta: Mapping[str, float]) -> dict[str, str]:
            return {
                t.ecm: with_params(t.source, {**tied_start[t.ecm], **theta}, filename=f"<{t.ecm}>")
                for t in request.tied
            }

        def run(theta: dict[str, float], seeds: Sequence[int]) -> tuple[list[Any], list[EpisodeEnd], str]:
            nonlocal episodes, env_steps
            cand = with_params(src, theta, filename=f"<{request.ecm}>")
            tied = {name: text.encode() for name, text in tied_sources(theta).items()}
            outcomes = self.evaluator.evaluate(
                request.task,
                request.versions,
                list(seeds),
                overrides={**request.companions, **tied, request.ecm: cand.encode()},
                override_origin=evaluation_origin or self.origin,
            )
            episodes += len(outcomes)
            env_steps += sum(int(o.steps) for o in outcomes)
            return list(outcomes), episode_ends(outcomes), cand

        for it in range(cfg.iterations):
            seeds = slices[it]
            if it > 0 and not affordable(cfg.population * len(seeds)):
                # a later iteration runs whole or not at all: its candidates replace the
                # finalists, and a few of them on fresh seeds are no better evidence
                stopped_by_budget = True
                break
            zs = [mean.copy()]
            for _ in range(cfg.population - 1):
                zs.append(np.clip(mean + sigma * rng.standard_normal(space.dim), zlo, zhi))
            scored: list[_Finalist] = []
            for i, z in enumerate(zs):
                if not affordable(len(seeds)):
                    stopped_by_budget = True
                    break
                theta = {**start, **space.params(z)}
                outcomes, ends, cand = run(theta, seeds)
                score = score_outcomes(outcomes, decomposition, ends=ends)
                passed = _passed(outcomes, ends, decomposition, ecm_index)
                scored.append(
                    _Finalist(
                        index=i,
                        theta=theta,
                        source=cand,
                        outcomes=outcomes,
                        ends=ends,
                        score=score,
                        passed=passed,
                        steps=_steps_in(ends, request.ecm),
                        unsafe=_unsafe_in(ends, request.ecm),
                    )
                )
                event = CemEvent(iteration=it, index=i, params=theta, score=score, seeds=seeds, passed=passed)
                history.append(event)
                if it == 0 and i == 0:
                    baseline = score
                if self.progress is not None:
                    self.progress(event)
            if not scored:
                break
            iterations_run += 1
            order = sorted(scored, key=lambda f: (f.rank(), -f.index), reverse=True)
            # the latest iteration's best are the finalists: later iterations sample around
            # better means, and the candidates of one iteration share their seeds
            finalists = order
            top_passed = order[0].passed
            elites = np.array([zs[f.index] for f in order[: cfg.n_elite]])
            a = cfg.smoothing
            # smoothed refit: a couple of elites would otherwise collapse sigma at once
            spread_now = elites.std(axis=0) if len(elites) > 1 else 0.5 * sigma
            mean = a * elites.mean(axis=0) + (1.0 - a) * mean
            sigma = np.maximum(a * spread_now + (1.0 - a) * sigma, cfg.sigma_min)
            log.info(
                "cem %s iteration %d: best %s (passed %.2f), mean now %s",
                request.ecm,
                it,
                order[0].score.to_dict(),
                top_passed,
                space.params(mean),
            )
            if stopped_by_budget:
                break
            if cfg.stop_when_passed and it + 1 >= cfg.min_iterations and top_passed >= 1.0:
                break
        if not finalists or baseline is None:  # pragma: no cover - iterations >= 1 always runs one
            raise Invalid("the search ran no iteration")
        best = finalists[0]
        if cfg.validation_episodes > 0 and cfg.validate_top > 1 and len(finalists) > 1:
            # one iteration's few episodes pick a lucky sample too often: the top few get
            # more episodes on fresh training seeds and are judged on all of theirs
            vseeds = _validation_seeds(request.train_seeds, cfg)
            judged = []
            for f in finalists[: cfg.validate_top]:
                if not affordable(len(vseeds)):
                    stopped_by_budget = True
                    break
                outcomes, ends, _ = run(f.theta, vseeds)
                all_out, all_ends = f.outcomes + outcomes, f.ends + ends
                judged.append(
                    _Finalist(
                        index=f.index,
                        theta=f.theta,
                        source=f.source,
                        outcomes=all_out,
                        ends=all_ends,
                        score=score_outcomes(all_out, decomposition, ends=all_ends),
                        passed=_passed(all_out, all_ends, decomposition, ecm_index),
                        steps=_steps_in(all_ends, request.ecm),
                        unsafe=_unsafe_in(all_ends, request.ecm),
                    )
                )
            # finalists the cap left unvalidated compete on their iteration episodes alone
            judged.extend(finalists[len(judged) : cfg.validate_top] if judged else ())
            judged.sort(key=lambda f: (f.rank(), -f.index), reverse=True)
            best = judged[0] if judged else best
        return CemResult(
            params=best.theta,
            source=best.source,
            score=best.score,
            baseline=baseline,
            iterations_run=iterations_run,
            episodes_run=episodes,
            env_steps_run=env_steps,
            stopped_by_budget=stopped_by_budget,
            history=tuple(history),
            experience=tuple(best.outcomes),
            tied_sources=tied_sources(best.theta),
        )

    # --- the learner -----------------------------------------------------------------

    def provenance(self, request: LearnRequest, *, extra: Mapping[str, Any] | None = None) -> Provenance:
        """Provenance of a candidate for ``request``: learner id, config hash, traces used."""
        config = {
            **self.config.to_dict(),
            "task": request.task,
            "ecm": request.ecm,
            "parent": request.parent.version,
            "train_seeds": list(request.train_seeds),
            **(extra or {}),
        }
        return Provenance(
            learner_id=self.learner_id, config_hash=config_hash(config), traces=trace_paths(request.outcomes)
        )

    def learn(self, request: LearnRequest) -> Candidate:
        """Search and return the best θ as a candidate (origin :attr:`origin`).

        Raises:
            Invalid, CapevoError: as :meth:`search`.
        """
        result = self.search(request)
        provenance = self.provenance(request)
        spec = candidate_spec(request, origin=self.origin, provenance=provenance)
        tied = tuple(
            Candidate(
                ecm=t.ecm,
                artifact=result.tied_sources[t.ecm].encode(),
                spec=_spec_from(t.parent, origin=self.origin, provenance=provenance),
                score=result.score,
                baseline=result.baseline,
                notes={"learner": self.learner_id, "params": dict(result.params), "tied_to": request.ecm},
            )
            for t in request.tied
        )
        return Candidate(
            ecm=request.ecm,
            artifact=result.source.encode(),
            spec=spec,
            score=result.score,
            baseline=result.baseline,
            notes={
                "learner": self.learner_id,
                "params": dict(result.params),
                "iterations_run": result.iterations_run,
                "episodes_run": result.episodes_run,
                "env_steps_run": result.env_steps_run,
                "stopped_by_budget": result.stopped_by_budget,
            },
            experience=result.experience,
            tied=tied,
        )


def candidate_spec(request: LearnRequest, *, origin: Origin, provenance: Provenance) -> PublishSpec:
    """The parent's descriptor and interface with a new origin, parent and provenance."""
    return _spec_from(request.parent, origin=origin, provenance=provenance)


def _spec_from(p: EcmVersion, *, origin: Origin, provenance: Provenance) -> PublishSpec:
    return PublishSpec(
        kind=p.kind,
        descriptor=p.descriptor,
        interface=p.interface,
        media_type=p.artifact.media_type,
        parent=p.version,
        origin=origin,
        provenance=provenance,
    )


def _tied_params(request: LearnRequest, start: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """Each tied ECM's current ``PARAMS``, checked to have exactly the searched ECM's names.

    Raises:
        Invalid: a tied ECM whose parameter names differ (it does not share the skill).
    """
    out: dict[str, dict[str, float]] = {}
    for t in request.tied:
        params = read_params(t.source, filename=f"<{t.ecm}>")
        if set(params) != set(start):
            raise Invalid(
                f"{t.ecm} cannot be tied to {request.ecm}: its parameters {sorted(params)} are not {sorted(start)}",
                details={"field": "tied"},
            )
        out[t.ecm] = params
    return out


def _passed(outcomes: Sequence[Any], ends: Sequence[Any], decomposition: Sequence[str], ecm_index: int) -> float:
    """Fraction of episodes that succeeded or started a step after the tuned one."""
    ecm = decomposition[ecm_index] if ecm_index >= 0 else ""
    return handover_rate(outcomes, decomposition, ecm, ends=ends)


def _steps_in(ends: Sequence[EpisodeEnd], ecm: str) -> float:
    """Mean environment steps per traced episode spent in ``ecm`` (0 without traces)."""
    if not ends:
        return 0.0
    return sum(e.ecm_steps.get(ecm, 0) for e in ends) / len(ends)


def _unsafe_in(ends: Sequence[EpisodeEnd], ecm: str) -> float:
    """Fraction of traced episodes with a step of ``ecm`` the safety monitor graded unsafe."""
    if not ends:
        return 0.0
    return sum(1 for e in ends if e.ecm_unsafe.get(ecm, 0) > 0) / len(ends)
