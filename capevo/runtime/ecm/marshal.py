"""Observation -> ECM inputs, and ECM output -> action vector, per the interface spec.

An :class:`IOSpec`'s ``name`` is the key of the environment's raw observation dict; its
``shape`` and ``dtype`` are what the ECM receives. Neural ECMs get the inputs concatenated
in interface order as one float32 vector; code ECMs get the dict.

Invariants:
1. :func:`marshal_inputs` returns exactly the declared keys, in interface order, each a
   read-only array of the declared shape and dtype holding the observation's values; or it
   raises :class:`Invalid` naming the key, expected and actual — never anything else.
2. :func:`flatten_inputs` is the concatenation of the marshalled arrays, raveled, as float32.
3. :func:`output_size` is the sum of the output specs' sizes; :func:`clip_to_bounds` clips
   each output spec's slice to its ``[low, high]`` and reports whether anything changed.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.records import IOSpec

_NUMERIC_KINDS = frozenset("biuf")


def spec_size(spec: IOSpec) -> int:
    """Number of scalars in one spec."""
    return math.prod(spec.shape)


def output_size(outputs: Sequence[IOSpec]) -> int:
    """Length of the flat action vector the outputs describe."""
    return sum(spec_size(s) for s in outputs)


def marshal_inputs(obs: Mapping[str, Any], inputs: Sequence[IOSpec], *, ecm: str = "ecm") -> dict[str, np.ndarray]:
    """Pick and check the ECM's inputs out of a raw observation dict.

    Args:
        obs: The environment's observation dict.
        inputs: The ECM's input specs.
        ecm: Name used in error messages.

    Returns:
        ``{spec.name: array}`` for every spec, arrays read-only.

    Raises:
        Invalid: a key is missing, a value is not numeric, or its shape differs.
    """
    if not isinstance(obs, Mapping):
        raise Invalid(f"{ecm}: observation must be a dict of arrays, got {type(obs).__name__}")
    out: dict[str, np.ndarray] = {}
    for spec in inputs:
        value = obs.get(spec.name) if type(obs) is dict else None
        # Fast path, every step of a running ECM: already an array of the declared dtype and shape.
        if type(value) is np.ndarray and value.dtype is _dtype(spec.dtype) and value.shape == spec.shape:
            view = value.view()
            view.flags.writeable = False
            out[spec.name] = view
            continue
        if spec.name not in obs:
            keys = ", ".join(sorted(map(str, obs))) or "none"
            raise Invalid(
                f"{ecm}: input {spec.name!r} is missing from the observation (keys: {keys})",
                details={"field": spec.name},
            )
        try:
            raw = np.asarray(obs[spec.name])
        except (TypeError, ValueError, OverflowError) as exc:
            raise Invalid(f"{ecm}: input {spec.name!r} is not an array: {exc}", details={"field": spec.name}) from None
        if raw.dtype.kind not in _NUMERIC_KINDS:
            raise Invalid(
                f"{ecm}: input {spec.name!r} has dtype {raw.dtype}, expected numeric ({spec.dtype})",
                details={"field": spec.name, "expected": spec.dtype, "got": str(raw.dtype)},
            )
        if raw.shape != tuple(spec.shape):
            raise Invalid(
                f"{ecm}: input {spec.name!r} has shape {raw.shape}, expected {tuple(spec.shape)}",
                details={"field": spec.name, "expected": list(spec.shape), "got": list(raw.shape)},
            )
        try:
            arr = raw.astype(spec.dtype, copy=False)
        except (TypeError, ValueError, OverflowError) as exc:
            raise Invalid(f"{ecm}: input {spec.name!r} cannot be cast to {spec.dtype}: {exc}") from None
        view = arr.view()
        view.flags.writeable = False  # the ECM must not scribble on the env's arrays
        out[spec.name] = view
    return out


@functools.lru_cache(maxsize=64)
def _dtype(name: str) -> np.dtype[Any] | None:
    try:
        return np.dtype(name)
    except TypeError:
        return None


def flatten_inputs(inputs: Mapping[str, np.ndarray], specs: Sequence[IOSpec]) -> np.ndarray:
    """The marshalled inputs concatenated in interface order as one float32 vector."""
    if not specs:
        return np.zeros(0, dtype=np.float32)
    return np.concatenate([np.ravel(inputs[s.name]).astype(np.float32, copy=False) for s in specs])


def clip_to_bounds(action: np.ndarray, outputs: Sequence[IOSpec]) -> tuple[np.ndarray, bool]:
    """Clip each output spec's slice of a flat action to its declared bounds.

    Returns:
        The (possibly new) array and whether any value was clipped.
    """
    try:
        bounds = _bounds(tuple(outputs), action.shape)
    except TypeError:  # an unhashable spec: work the bounds out for this call only
        bounds = _bounds.__wrapped__(tuple(outputs), action.shape)
    if bounds is None:
        return action, False
    lows, highs = bounds
    clipped = np.clip(action, lows, highs)
    return clipped, bool((clipped != action).any())


@functools.lru_cache(maxsize=256)
def _bounds(outputs: tuple[IOSpec, ...], shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-element lower and upper bounds of a flat action (read-only), or None if unbounded.

    Cached: an invoker clips every step with the same interface.
    """
    if not any(s.low is not None or s.high is not None for s in outputs):
        return None
    lows = np.full(shape, -np.inf)
    highs = np.full(shape, np.inf)
    i = 0
    for s in outputs:
        n = spec_size(s)
        if s.low is not None:
            lows[i : i + n] = s.low
        if s.high is not None:
            highs[i : i + n] = s.high
        i += n
    lows.flags.writeable = False
    highs.flags.writeable = False
    return lows, highs
