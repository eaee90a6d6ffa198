"""Experience for learners: the ``/env/step`` records of traces as arrays of transitions.

Arrays of a :class:`Transitions` (row ``i`` is one env step; N rows):

==========  ============  =========  ===================================================
name        shape         dtype      meaning
==========  ============  =========  ===================================================
obs         (N, D)        float32    observation before the step
action      (N, A)        float32    action executed (after governance)
reward      (N,)          float32    reward of the step
next_obs    (N, D)        float32    observation after the step
done        (N,)          bool       terminated or truncated
terminated  (N,)          bool       the episode ended in a terminal state
truncated   (N,)          bool       the episode was cut off (horizon, budget)
is_success  (N,)          bool       the task reported success after the step
ecm         (N,)          str (<U)   ECM that produced the action
version     (N,)          int64      version of that ECM
episode     (N,)          int64      episode index within its run
step        (N,)          int64      step index within its episode
run_id      (N,)          str (<U)   run that wrote the trace (episodes repeat across runs)
==========  ============  =========  ===================================================

A non-finite value in a trace (written as ``null``) comes back as NaN. ``.npz`` files hold
exactly these names (no pickled objects); ``.jsonl`` files hold one JSON object per row
with the same keys.

Invariants:
1. All arrays of a :class:`Transitions` have the same first dimension N, the dtypes above,
   and are read-only.
2. Rows follow file order (paths in the order given, records in write order), so
   consecutive rows of one episode are consecutive steps.
3. ``Transitions.load_npz(p)`` after ``t.save_npz(p)`` equals ``t`` array by array.
4. Mixed observation or action lengths raise :class:`Invalid` naming the first offending
   step, never a ragged or object array.
5. ``parse_episodes(spec)`` contains exactly the integers the spec lists (``all`` or
   ``""``: every episode); ``str(parse_episodes(s))`` parses back to an equal selection.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Collection, Container, Iterable, Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from capevo.errors import Corrupt, Invalid, Unavailable
from capevo.runtime.traces.reader import TraceReader
from capevo.runtime.traces.records import EnvStep

EXPORT_FORMATS: tuple[str, ...] = ("npz", "jsonl")

# Format strings per vector length: "%.9g,%.9g,...". A handful of lengths occur per export.
_VECTOR_FORMATS: dict[int, str] = {}


def format_vector(values: Sequence[float]) -> str:
    """Comma-separated ``%.9g`` numbers (``null`` for non-finite ones), without brackets: nine
    significant digits name each float32 uniquely."""
    if type(values) is not tuple:
        values = tuple(values)
    n = len(values)
    fmt = _VECTOR_FORMATS.get(n)
    if fmt is None:
        fmt = _VECTOR_FORMATS[n] = ",".join(["%.9g"] * n)
    text = fmt % values
    # %g prints only digits, sign, '.', 'e' and '+' for finite values: an 'n' means nan or inf.
    if "n" in text:
        text = ",".join(f"{v:.9g}" if math.isfinite(v) else "null" for v in values)
    return text


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Transitions:
    """Transitions exported from traces; see the module docstring for the arrays.

    Raises:
        Invalid: arrays of different lengths or wrong rank.
    """

    ARRAYS: ClassVar[tuple[str, ...]] = (
        "obs",
        "action",
        "reward",
        "next_obs",
        "done",
        "terminated",
        "truncated",
        "is_success",
        "ecm",
        "version",
        "episode",
        "step",
        "run_id",
    )

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    done: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    is_success: np.ndarray
    ecm: np.ndarray
    version: np.ndarray
    episode: np.ndarray
    step: np.ndarray
    run_id: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.reward)
        for f in fields(self):
            a = getattr(self, f.name)
            rank = 2 if f.name in ("obs", "action", "next_obs") else 1
            if not isinstance(a, np.ndarray) or a.ndim != rank or len(a) != n:
                raise Invalid(
                    f"transitions array {f.name!r} must be a rank-{rank} array with {n} rows",
                    details={"field": f.name},
                )
            a.setflags(write=False)

    def __len__(self) -> int:
        return len(self.reward)

    def arrays(self) -> dict[str, np.ndarray]:
        """``{name: array}`` in :attr:`ARRAYS` order."""
        return {name: getattr(self, name) for name in self.ARRAYS}

    def equals(self, other: Transitions) -> bool:
        """Same arrays (NaN equal to NaN)."""
        return all(
            a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
            for a, b in zip(self.arrays().values(), other.arrays().values(), strict=True)
        )

    @classmethod
    def from_steps(cls, steps: Iterable[tuple[str, EnvStep]]) -> Transitions:
        """Build from ``(run_id, step)`` pairs.

        Raises:
            Invalid: observation or action lengths differ between steps (invariant 4).
        """
        cols: dict[str, list[Any]] = {name: [] for name in cls.ARRAYS}
        dims: dict[str, int] = {}
        for run_id, s in steps:
            for name, vec in (("obs", s.obs), ("next_obs", s.next_obs), ("action", s.action)):
                key = "action" if name == "action" else "obs"
                if dims.setdefault(key, len(vec)) != len(vec):
                    raise Invalid(
                        f"{name} of run {run_id} episode {s.episode} step {s.step} has {len(vec)} values, "
                        f"earlier steps have {dims[key]}; export one ECM or task at a time",
                        details={"field": name, "episode": s.episode, "step": s.step},
                    )
                cols[name].append(vec)
            cols["reward"].append(s.reward)
            cols["done"].append(s.terminated or s.truncated)
            cols["terminated"].append(s.terminated)
            cols["truncated"].append(s.truncated)
            cols["is_success"].append(s.is_success)
            cols["ecm"].append(s.ecm)
            cols["version"].append(s.version)
            cols["episode"].append(s.episode)
            cols["step"].append(s.step)
            cols["run_id"].append(run_id)
        obs_dim = dims.get("obs", 0)
        act_dim = dims.get("action", 0)

        def matrix(name: str, width: int) -> np.ndarray:
            return np.asarray(cols[name], dtype=np.float32).reshape(len(cols[name]), width)

        def text(name: str) -> np.ndarray:
            return np.asarray(cols[name], dtype=str) if cols[name] else np.zeros(0, dtype="<U1")

        return cls(
            obs=matrix("obs", obs_dim),
            action=matrix("action", act_dim),
            reward=np.asarray(cols["reward"], dtype=np.float32),
            next_obs=matrix("next_obs", obs_dim),
            done=np.asarray(cols["done"], dtype=bool),
            terminated=np.asarray(cols["terminated"], dtype=bool),
            truncated=np.asarray(cols["truncated"], dtype=bool),
            is_success=np.asarray(cols["is_success"], dtype=bool),
            ecm=text("ecm"),
            version=np.asarray(cols["version"], dtype=np.int64),
            episode=np.asarray(cols["episode"], dtype=np.int64),
            step=np.asarray(cols["step"], dtype=np.int64),
            run_id=text("run_id"),
        )

    # -- files -----------------------------------------------------------------------------

    def save_npz(self, path: str | os.PathLike[str]) -> Path:
        """Write the arrays to ``path`` (compressed npz, no pickles), atomically."""
        return _atomic_write(Path(path), lambda f: np.savez_compressed(f, **self.arrays()))

    def save_jsonl(self, path: str | os.PathLike[str]) -> Path:
        """Write one JSON object per transition to ``path``, atomically."""
        return _atomic_write(Path(path), lambda f: f.writelines(line.encode() for line in self.jsonl_lines()))

    def jsonl_lines(self) -> Iterator[str]:
        """One strict-JSON line per transition (floats with 9 significant digits)."""
        for i in range(len(self)):
            reward = format_vector((float(self.reward[i]),))
            yield (
                f'{{"run_id":{json.dumps(str(self.run_id[i]))},"episode":{int(self.episode[i])},'
                f'"step":{int(self.step[i])},"ecm":{json.dumps(str(self.ecm[i]))},"version":{int(self.version[i])},'
                f'"obs":[{format_vector(self.obs[i].tolist())}],"action":[{format_vector(self.action[i].tolist())}],'
                f'"reward":{reward},"next_obs":[{format_vector(self.next_obs[i].tolist())}],'
                f'"done":{_js(self.done[i])},"terminated":{_js(self.terminated[i])},'
                f'"truncated":{_js(self.truncated[i])},"is_success":{_js(self.is_success[i])}}}\n'
            )

    @classmethod
    def load_npz(cls, path: str | os.PathLike[str]) -> Transitions:
        """Read a file written by :meth:`save_npz`.

        Raises:
            NotFound-like OS errors as :class:`Invalid`; Corrupt: an array is missing.
        """
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                missing = [name for name in cls.ARRAYS if name not in data.files]
                if missing:
                    raise Corrupt(f"{path} is not a transitions file: missing arrays {', '.join(missing)}")
                return cls(**{name: data[name] for name in cls.ARRAYS})
        except (OSError, ValueError) as exc:
            raise Invalid(f"cannot read transitions from {path}: {exc}") from None


_EPISODE_PART = re.compile(r"\s*(\d{1,18})\s*(?:-\s*(\d{1,18})\s*)?", re.ASCII)


@dataclass(frozen=True, slots=True)
class EpisodeSelection:
    """Episodes chosen by inclusive ranges; ``ranges=None`` means all episodes."""

    ranges: tuple[tuple[int, int], ...] | None

    def __contains__(self, episode: object) -> bool:
        if self.ranges is None:
            return True
        return isinstance(episode, int) and any(lo <= episode <= hi for lo, hi in self.ranges)

    def __str__(self) -> str:
        if self.ranges is None:
            return "all"
        return ",".join(str(lo) if lo == hi else f"{lo}-{hi}" for lo, hi in self.ranges)


def parse_episodes(spec: str) -> EpisodeSelection:
    """Parse an episode selection: ``all``, or comma-separated indices and ranges ``0,3,5-9``.

    Raises:
        Invalid: a part is not a non-negative integer or an ``a-b`` range with ``a <= b``.
    """
    text = spec.strip().lower()
    if text in ("", "all", "*"):
        return EpisodeSelection(None)
    ranges: list[tuple[int, int]] = []
    for part in text.split(","):
        m = _EPISODE_PART.fullmatch(part)
        lo = int(m.group(1)) if m else 0
        hi = int(m.group(2)) if m and m.group(2) is not None else lo
        if m is None or lo > hi:
            raise Invalid(
                f"bad episode selection {spec!r} at {part.strip()!r}: use 'all' or indices and ranges like 0,3,5-9",
                details={"field": "episodes"},
            )
        ranges.append((lo, hi))
    return EpisodeSelection(tuple(ranges))


def _js(flag: Any) -> str:
    return "true" if bool(flag) else "false"


def _atomic_write(path: Path, write: Any) -> Path:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tmp.open("wb") as f:
            write(f)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise Unavailable(f"cannot write {path}: {exc.strerror or exc}") from None
    return path


def _as_paths(paths: str | os.PathLike[str] | Iterable[str | os.PathLike[str]]) -> list[Path]:
    if isinstance(paths, str | os.PathLike):
        return [Path(paths)]
    return [Path(p) for p in paths]


def iter_env_steps(
    paths: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    *,
    episodes: Container[int] | None = None,
    ecms: Collection[str] | None = None,
    allow_incomplete: bool = False,
) -> Iterator[tuple[str, EnvStep]]:
    """``(run_id, env step)`` of every selected step of the traces, in file order."""
    for path in _as_paths(paths):
        reader = TraceReader(path, allow_incomplete=allow_incomplete)
        run_id = reader.metadata().run_id
        for s in reader.env_steps():
            if episodes is not None and s.episode not in episodes:
                continue
            if ecms is not None and s.ecm not in ecms:
                continue
            yield run_id, s


def export_transitions(
    paths: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    *,
    episodes: Container[int] | None = None,
    ecms: Collection[str] | None = None,
    allow_incomplete: bool = False,
) -> Transitions:
    """The transitions of one or more trace files, for learners.

    Args:
        paths: A trace file or several; rows follow this order.
        episodes: Keep only these episode indices (None: all).
        ecms: Keep only steps whose action came from these ECMs (None: all).
        allow_incomplete: Read unfinished (crashed) files up to the damage.

    Returns:
        :class:`Transitions` (possibly empty).

    Raises:
        NotFound, Invalid, Forbidden: a path is missing, not an MCAP file or unreadable.
        Corrupt: a file is unfinished (and ``allow_incomplete`` is false) or damaged.
        Invalid: observation or action lengths differ between selected steps.
    """
    return Transitions.from_steps(
        iter_env_steps(paths, episodes=episodes, ecms=ecms, allow_incomplete=allow_incomplete)
    )
