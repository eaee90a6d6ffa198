"""Rows: the episode loop's form of an env step or an ECM invocation, a plain tuple of fields.

Every robosuite step evicts the CPU caches, so whatever the loop runs for traces between two
steps runs cold: building a frozen 12-field record there cost about 20 µs per step, a tuple of
the same fields a fraction of that (benchmarks/bench_traces_loop.py). The loop therefore hands
sinks rows (:meth:`~capevo.runtime.traces.sink.TraceSink.write_env_step_row`,
:meth:`~capevo.runtime.traces.sink.TraceSink.write_invocation_row`); the writer encodes them in
batches, warm, and only what reads a trace back ever sees a record.

A row holds its fields in the record's field order, except that an env step row ends with the
arms of the robot state (anything with ``eef_pos`` and ``eef_force`` vectors) instead of the
key state built from them; :func:`key_state_of` builds it, wherever a record is needed. An
invocation row's input is given one of three ways, its record's ``input_state`` in each case a
read-only float32 array or the vector itself:

- the step's flat observation and ``input_index``, the positions of the ECM's inputs in it
  (:func:`observation_index`, once per ECM activation): the input costs the loop nothing, and the
  encoder prints it from the observation's text, which the env step prints anyway;
- ``bytes`` of packed native float32 values, what :func:`input_state_of` makes in one C call
  (``input_index`` None), where the inputs are not all in the flat observation;
- any vector (``input_index`` None).

Invariants:
1. ``env_step_of(row)`` is the record the row stands for; its ``key_state`` is
   ``key_state_of(arms)``: ``arm{i}_eef_pos`` and ``arm{i}_eef_force`` for arm ``i``, in order.
2. ``invocation_of(row)`` is ``EcmInvocation`` of the row's fields but ``input_index``, its input
   ``input_state[list(input_index)]`` as float32 where ``input_index`` is not None, packed input
   bytes read as a read-only float32 array.
3. A row is read, never changed; its vectors must not change after the row is handed over
   (the loop passes read-only arrays and tuples).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, TypeAlias

import numpy as np

from capevo.errors import Invalid
from capevo.runtime.traces.native import NATIVE
from capevo.runtime.traces.records import EcmInvocation, EnvStep, FloatVector, Outcome


class ArmVectors(Protocol):
    """What a key state is built from: one arm's end-effector vectors."""

    @property
    def eef_pos(self) -> tuple[float, ...]: ...

    @property
    def eef_force(self) -> tuple[float, ...]: ...


EnvStepRow: TypeAlias = tuple[
    int,  # episode
    int,  # step
    str,  # ecm
    int,  # version
    FloatVector,  # obs
    tuple[float, ...],  # action
    float,  # reward
    FloatVector,  # next_obs
    bool,  # terminated
    bool,  # truncated
    bool,  # is_success
    Sequence[ArmVectors],  # arms, whose vectors make the key state
]
InvocationRow: TypeAlias = tuple[
    int,  # episode
    int,  # step
    str,  # ecm
    int,  # version
    "FloatVector | bytes",  # input_state, or the observation input_index selects from (bytes: packed float32)
    "tuple[int, ...] | None",  # input_index
    "tuple[float, ...] | None",  # output
    float,  # duration_s
    Outcome,  # outcome
    "str | None",  # error
]

ENV_STEP_ROW_LEN = 12
INVOCATION_ROW_LEN = 10


def arm_keys(i: int) -> tuple[str, str]:
    """The key-state names of arm ``i`` (csrc/rows.c spells them too)."""
    return f"arm{i}_eef_pos", f"arm{i}_eef_force"


def key_state_of(arms: Sequence[ArmVectors]) -> dict[str, tuple[float, ...]]:
    """The key state of an env step: each arm's end-effector position and force."""
    out: dict[str, tuple[float, ...]] = {}
    for i, arm in enumerate(arms):
        pos, force = arm_keys(i)
        out[pos] = arm.eef_pos
        out[force] = arm.eef_force
    return out


def concatenated_input(obs: Mapping[str, np.ndarray], keys: tuple[str, ...]) -> FloatVector:
    """:func:`input_state_of` with numpy: one read-only float32 array (``()`` for no values)."""
    parts = [obs[k] for k in keys if k in obs]
    if not parts:
        return ()
    # axis=None flattens as it concatenates: one numpy call, not one ravel per key.
    flat = np.concatenate(parts, axis=None)
    flat.flags.writeable = False
    return flat


if NATIVE is not None:
    NATIVE.configure_pack(concatenated_input)
input_state_of: Callable[[Mapping[str, np.ndarray], tuple[str, ...]], FloatVector | bytes] = (
    concatenated_input if NATIVE is None else NATIVE.pack_float32
)
"""The flat input an ECM with inputs ``keys`` saw, for its invocation row: the float32 values of
each key ``obs`` has, in order, flattened. Where the C part is built, one C call packs them into
bytes when ``obs`` is a dict of C-contiguous float32 arrays (the env's observations) and leaves
anything else to :func:`concatenated_input`; where it is not, :func:`concatenated_input`."""


def check_row(row: Any, length: int, method: str) -> None:
    """Raise :class:`Invalid` unless ``row`` is a tuple of ``length`` fields (shared by the sinks)."""
    if type(row) is not tuple or len(row) != length:
        got = f"a tuple of {len(row)}" if isinstance(row, tuple) else f"a {type(row).__name__}"
        raise Invalid(
            f"{method} takes a tuple of {length} fields, got {got}",
            details={"field": "row", "expected": f"tuple[{length}]"},
        )


def env_step_of(row: EnvStepRow) -> EnvStep:
    """The env step record ``row`` stands for.

    Raises:
        Invalid: the arms have no ``eef_pos``/``eef_force`` vectors.
    """
    episode, step, ecm, version, obs, action, reward, next_obs, terminated, truncated, is_success, arms = row
    try:
        key_state = key_state_of(arms)
    except (TypeError, AttributeError) as exc:
        raise Invalid(
            f"an env step row's arms need eef_pos and eef_force: {type(exc).__name__}: {exc}",
            details={"field": "arms"},
        ) from None
    return EnvStep(
        episode=episode,
        step=step,
        ecm=ecm,
        version=version,
        obs=obs,
        action=action,
        reward=reward,
        next_obs=next_obs,
        terminated=terminated,
        truncated=truncated,
        is_success=is_success,
        key_state=key_state,
    )


def invocation_of(row: InvocationRow) -> EcmInvocation:
    """The invocation record ``row`` stands for.

    Raises:
        Invalid: packed input bytes whose length is not a whole number of float32 values; an
            ``input_index`` that is not a tuple of positions in the observation.
    """
    episode, step, ecm, version, input_state, input_index, output, duration_s, outcome, error = row
    if input_index is not None:
        input_state = select_input(input_state, input_index)
    elif type(input_state) is bytes:
        if len(input_state) % 4:
            raise Invalid(
                f"an invocation row's packed input holds {len(input_state)} bytes, not whole float32 values",
                details={"field": "input_state"},
            )
        input_state = np.frombuffer(input_state, dtype=np.float32)  # read-only: bytes are immutable
    return EcmInvocation(
        episode=episode,
        step=step,
        ecm=ecm,
        version=version,
        input_state=input_state,
        output=output,
        duration_s=duration_s,
        outcome=outcome,
        error=error,
    )


def select_input(observation: Any, input_index: Any) -> np.ndarray:
    """The float32 values of a flat ``observation`` at the positions ``input_index``, read-only.

    Raises:
        Invalid: ``input_index`` is not a tuple of ints, each a position in ``observation``.
    """
    try:
        with np.errstate(over="ignore"):  # beyond float32's range: inf, as the codec rounds it
            values = np.asarray(observation, dtype=np.float32).reshape(-1)
        if type(input_index) is not tuple or not all(type(i) is int and 0 <= i < len(values) for i in input_index):
            raise IndexError(f"{input_index!r} holds what is not a position in {len(values)} values")
    except (TypeError, ValueError, IndexError) as exc:
        raise Invalid(
            f"an invocation row's input_index does not select from its observation: {exc}",
            details={"field": "input_index"},
        ) from None
    selected = values[list(input_index)]
    selected.flags.writeable = False
    return selected


def observation_index(
    obs: Mapping[str, np.ndarray], flat_keys: Sequence[str], keys: tuple[str, ...]
) -> tuple[int, ...] | None:
    """The positions in the flat observation (``obs``'s ``flat_keys``, each flattened, concatenated)
    of the values :func:`input_state_of` packs for ``keys``; None where one of the keys ``obs`` has
    is not in the flat observation."""
    offsets: dict[str, range] = {}
    at = 0
    for k in flat_keys:
        size = int(np.size(obs[k]))
        offsets[k] = range(at, at + size)
        at += size
    index: list[int] = []
    for k in keys:
        if k not in obs:
            continue  # input_state_of leaves it out too
        if k not in offsets:
            return None
        index.extend(offsets[k])
    return tuple(index)
