"""JSON encoding of trace records for MCAP ``json`` channels, with fast paths for hot topics.

``/env/step`` (every control step) and ``/ecm/invocation`` (every ECM call) are encoded with
one :func:`orjson.dumps` call each. Per call costs dominate on records this size (numpy and
orjson each cost about as much per call as per 40 values), so the fast paths make as few
calls as they can (benchmarks/bench_traces.py, bench_traces_loop.py):

- Observation vectors (``obs``, ``next_obs``, ``input_state``) are float32 data: a 1-D float32
  array (what the episode loop passes, see :data:`~capevo.runtime.traces.records.FloatVector`)
  goes to orjson as it is, anything else is rounded to float32 in one ``array("f")``
  conversion; orjson prints the shortest text that names each float32.
- The runtime's own float64 vectors (``action``, ``key_state``, ``output``) are printed
  exactly, shortest repr, when they are tuples of floats (a float32 conversion would cost more
  than the characters it saves); anything else is rounded to float32.

Records' ``from_dict`` rounds every vector to float32, the precision the runtime works in.

Rows (:mod:`capevo.runtime.traces.rows`, what the episode loop hands the writer) are encoded a
batch at a time by :meth:`RecordEncoder.rows`: one ``orjson.dumps`` prints every vector of the
batch once (one step's ``next_obs`` is the next step's ``obs`` and often an ECM's input), and
each payload is spliced from those texts, the payload of the row's record (invariant 6); an
ECM input the row gives as positions in the observation is cut from the observation's text.
The splicing is C (``csrc/rows.c``) where it is built; :meth:`RecordEncoder.rows_in_python` is
its specification.

Whatever the fast path cannot print exactly goes through the template path instead, which
splices per-field text into one bytes template: a record whose ints or names are not exactly
``int``/``str``, and any payload that would contain ``null`` where the record has no None (a
non-finite value, or a finite float64 beyond float32's range, which the template prints with
nine significant digits so it stays finite). ``/governance/intervention`` (at most a few per
step) always takes the template path; plan steps and episode summaries (rare, no vectors) go
through :mod:`json`.

Invariants:
1. Every payload is strict JSON (RFC 8259): no ``NaN``/``Infinity`` tokens; a non-finite
   float becomes ``null`` (decoded as NaN).
2. A fast path, the template path and the generic ``json`` path of the same record decode to
   the same record (for float64 vector values: each within one float32 ulp).
3. ``decode(topic, encode(r)) == r`` for every record ``r`` with finite floats whose vectors
   hold float32 values; a float64 vector value comes back as a float32 within one float32
   ulp of it (beyond float32's range, within nine significant digits); scalar floats come
   back exactly.
4. The float32 cache never serves stale values: it is keyed by the identity of a *tuple*
   (immutable) that the encoder keeps alive, so the key cannot be reused for other content.
5. A vector component that is not a real number (a string, None, a sequence, a complex
   number) fails the encoding, as it would fail ``%g``.
6. ``rows(batch)[i]`` is ``env_step(env_step_of(row))`` or ``invocation(invocation_of(row))``
   for the ``i``-th row, or the :class:`Invalid` those raise, with the C splicer and without;
   only where a name or an error's text holds ``null`` (which sends a record to the template
   path) are the bytes other ones that decode to the same record.
"""

from __future__ import annotations

import json
import math
from array import array
from collections.abc import Sequence
from typing import Any

import numpy as np
import orjson

from capevo.errors import Corrupt, Invalid
from capevo.runtime.traces.native import NATIVE
from capevo.runtime.traces.records import (
    EcmInvocation,
    EnvStep,
    Intervention,
    Outcome,
    TraceRecord,
    record_type,
)
from capevo.runtime.traces.rows import EnvStepRow, InvocationRow, arm_keys, env_step_of, invocation_of

_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False, check_circular=False, ensure_ascii=False)

# Format strings per vector length: "%.9g,%.9g,...". A handful of lengths occur per run.
_VECTOR_FORMATS: dict[int, str] = {}

_ENV_STEP_TEMPLATE = (
    b'{"episode":%d,"step":%d,"ecm":%b,"version":%d,"obs":%b,"action":%b,"reward":%b,'
    b'"next_obs":%b,"terminated":%b,"truncated":%b,"is_success":%b,"key_state":{%b}}'
)
_INVOCATION_TEMPLATE = (
    b'{"episode":%d,"step":%d,"ecm":%b,"version":%d,"input_state":%b,"output":%b,'
    b'"duration_s":%b,"outcome":%b,"error":%b}'
)
# The row path's templates: vectors arrive as the text between their brackets.
_ENV_STEP_ROW_TEMPLATE = (
    b'{"episode":%d,"step":%d,"ecm":%b,"version":%d,"obs":[%b],"action":[%b],"reward":%b,'
    b'"next_obs":[%b],"terminated":%b,"truncated":%b,"is_success":%b,"key_state":{%b}}'
)
_INVOCATION_ROW_TEMPLATE = (
    b'{"episode":%d,"step":%d,"ecm":%b,"version":%d,"input_state":[%b],"output":%b,'
    b'"duration_s":%b,"outcome":%b,"error":%b}'
)
_INTERVENTION_TEMPLATE = (
    b'{"episode":%d,"step":%d,"constraint":%b,"original_action":%b,"result_action":%b,"reason":%b,"enforced":%b}'
)
_OUTCOMES = {o: json.dumps(o.value).encode() for o in Outcome}
_OUTCOME_VALUES = {o: o.value for o in Outcome}
_BOOLS = (b"false", b"true")
_NUMPY = orjson.OPT_SERIALIZE_NUMPY
_FLOAT32 = np.float32
_PLAIN_FLOAT = frozenset((float,))

_MAX_CACHED_NAMES = 4096
_SHORT_VECTOR = 10
"""Below this length ``%.9g`` is cheaper than the float32 array round trip (measured: 1.0 against
2.0 µs for 3 values, 2.7 against 2.4 µs for 12)."""


def format_vector(values: Sequence[float]) -> str:
    """Comma-separated ``%.9g`` numbers (``null`` for non-finite ones), without brackets."""
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


def vector_json(values: Sequence[float]) -> bytes:
    """The JSON array of ``values`` as float32, shortest text per value (see the module docstring).

    Raises:
        TypeError: a component is not a real number.
        OverflowError: an integer component too large for a float.
    """
    if len(values) < _SHORT_VECTOR:
        return b"[" + format_vector(values).encode() + b"]"
    # array("f") accepts exactly what %g accepts (real numbers) and rounds each to float32
    # correctly; a value it cannot hold becomes inf, which orjson prints as null.
    text = orjson.dumps(np.frombuffer(array("f", values), dtype=_FLOAT32), option=_NUMPY)
    if b"null" in text:
        return b"[" + format_vector(values).encode() + b"]"
    return text


def _format_float(value: float) -> bytes:
    value = float(value)
    # inf - inf and nan - nan are nan, which is never equal to 0.0.
    return repr(value).encode() if value - value == 0.0 else b"null"


def _not_encodable(record: object, exc: Exception) -> Invalid:
    return Invalid(
        f"{type(record).__name__} does not encode as JSON: {type(exc).__name__}: {exc}",
        details={"record": type(record).__name__},
    )


def float32_array(values: Sequence[float] | np.ndarray) -> np.ndarray:
    """``values`` rounded to float32 (one conversion; orjson prints the result).

    A 1-D C-contiguous float32 array (the env's observations) is returned as it is; ``bytes``
    are read as packed native float32 values (ValueError unless a whole number of them).

    Raises:
        TypeError: a component is not a real number (``array("f")`` accepts exactly what ``%g``
            accepts); a value beyond float32's range becomes an infinity.
        OverflowError: an integer component too large for a float.
    """
    if type(values) is np.ndarray and values.dtype == _FLOAT32 and values.ndim == 1 and values.flags.c_contiguous:
        return values
    if type(values) is bytes:  # an invocation row's packed input (capevo.runtime.traces.rows)
        return np.frombuffer(values, dtype=_FLOAT32)
    return np.frombuffer(array("f", values), dtype=_FLOAT32)


def _exact_or_float32(values: Sequence[float]) -> Any:
    """``values`` itself if it is a tuple of floats (orjson prints each exactly), else float32."""
    if type(values) is tuple and set(map(type, values)) <= _PLAIN_FLOAT:
        return values
    return float32_array(values)


def _error_json(error: object) -> bytes:
    return orjson.dumps(str(error))


_native = NATIVE  # None in a source tree nobody built: RecordEncoder.rows_in_python does the work


def _array_probes() -> list[np.ndarray]:
    """Arrays the C splicer reads numpy's array head on at configuration, checking its reading
    against the buffer protocol's: each way float32 vectors are and are not what it prints as
    they are (it asks the buffer protocol instead where the two disagree)."""
    plain = np.arange(6, dtype=_FLOAT32)
    return [plain, plain[::2], plain.reshape(2, 3), plain.astype(np.float64), plain.astype(">f4"), plain[1:4]]


ARRAY_HEAD_READ = False
"""Whether the C splicer tells float32 vectors by numpy's array head (else by a buffer request)."""
if _native is not None:
    ARRAY_HEAD_READ = _native.configure_rows(
        orjson.dumps,
        _NUMPY,
        float32_array,
        _exact_or_float32,
        _OUTCOMES,
        _error_json,
        np.ndarray,
        np.dtype(_FLOAT32),
        _array_probes(),
    )


def rows_kernel_available() -> bool:
    """Whether the C row splicer is built (else rows are spliced in Python, slower)."""
    return _native is not None


class RecordEncoder:
    """Encodes trace records; keep one per writer so its caches stay warm.

    Args:
        kernel: Splice rows with the C splicer where it is built (False: in Python, to compare).
    """

    __slots__ = ("_kernel", "_last_next_obs", "_names")

    def __init__(self, *, kernel: bool = True) -> None:
        self._kernel = kernel
        self._names: dict[str, bytes] = {}
        # (tuple, its float32 view) as one attribute: one assignment, so threads sharing the
        # encoder can never pair a tuple with another tuple's values.
        self._last_next_obs: tuple[tuple[float, ...] | None, np.ndarray | None] = (None, None)

    def name_json(self, name: str) -> bytes:
        """The JSON string of ``name`` (cached for the names a run repeats)."""
        text = self._names.get(name)
        if text is None:
            if not isinstance(name, str):
                raise TypeError(f"a name must be a str, got {type(name).__name__}")
            text = orjson.dumps(name)
            if len(self._names) < _MAX_CACHED_NAMES:
                self._names[name] = text
        return text

    def encode(self, record: TraceRecord) -> bytes:
        """The JSON payload of any trace record.

        Raises:
            Invalid: a field has a type JSON cannot carry (e.g. a string where a number belongs).
        """
        try:
            if isinstance(record, EnvStep):
                return self._env_step(record)
            if isinstance(record, EcmInvocation):
                return self._invocation(record)
            if isinstance(record, Intervention):
                return self._intervention(record)
            return encode_dict(record.to_dict())
        except (TypeError, ValueError, OverflowError) as exc:
            raise _not_encodable(record, exc) from None

    def env_step(self, s: EnvStep) -> bytes:
        """:meth:`encode` for an env step (the writer's hot path skips the dispatch)."""
        try:
            return self._env_step(s)
        except (TypeError, ValueError, OverflowError) as exc:
            raise _not_encodable(s, exc) from None

    def _env_step(self, s: EnvStep) -> bytes:
        if (
            type(s.episode) is not int
            or type(s.step) is not int
            or type(s.version) is not int
            or type(s.ecm) is not str
        ):
            return self._env_step_template(s)
        obs, next_obs = s.obs, s.next_obs
        last_obs, last_view = self._last_next_obs
        obs_view = last_view if obs is last_obs and type(obs) is tuple else float32_array(obs)
        next_view = float32_array(next_obs)
        self._last_next_obs = (next_obs, next_view) if type(next_obs) is tuple else (None, None)
        payload = orjson.dumps(
            {
                "episode": s.episode,
                "step": s.step,
                "ecm": s.ecm,
                "version": s.version,
                "obs": obs_view,
                "action": _exact_or_float32(s.action),
                "reward": float(s.reward),
                "next_obs": next_view,
                "terminated": bool(s.terminated),
                "truncated": bool(s.truncated),
                "is_success": bool(s.is_success),
                "key_state": {k: _exact_or_float32(v) for k, v in s.key_state.items()},
            },
            option=_NUMPY,
        )
        # No field of an env step is None: any null is a value the template must print.
        return self._env_step_template(s) if b"null" in payload else payload

    def _env_step_template(self, s: EnvStep) -> bytes:
        key_state = b""
        if s.key_state:
            key_state = b",".join(self.name_json(k) + b":" + vector_json(v) for k, v in s.key_state.items())
        return _ENV_STEP_TEMPLATE % (
            s.episode,
            s.step,
            self.name_json(s.ecm),
            s.version,
            vector_json(s.obs),
            vector_json(s.action),
            _format_float(s.reward),
            vector_json(s.next_obs),
            _BOOLS[bool(s.terminated)],
            _BOOLS[bool(s.truncated)],
            _BOOLS[bool(s.is_success)],
            key_state,
        )

    def invocation(self, r: EcmInvocation) -> bytes:
        """:meth:`encode` for an ECM invocation (the writer's hot path skips the dispatch)."""
        try:
            return self._invocation(r)
        except (TypeError, ValueError, OverflowError) as exc:
            raise _not_encodable(r, exc) from None

    def _invocation(self, r: EcmInvocation) -> bytes:
        outcome = _OUTCOME_VALUES.get(r.outcome)  # a str enum: members and their values both hit
        if (
            outcome is None
            or type(r.episode) is not int
            or type(r.step) is not int
            or type(r.version) is not int
            or type(r.ecm) is not str
        ):
            return self._invocation_template(r)
        output, error, inputs = r.output, r.error, r.input_state
        last_obs, last_view = self._last_next_obs
        input_view = last_view if inputs is last_obs and type(inputs) is tuple else float32_array(inputs)
        output_view = None if output is None else _exact_or_float32(output)
        payload = orjson.dumps(
            {
                "episode": r.episode,
                "step": r.step,
                "ecm": r.ecm,
                "version": r.version,
                "input_state": input_view,
                "output": output_view,
                "duration_s": float(r.duration_s),
                "outcome": outcome,
                "error": None if error is None else str(error),
            },
            option=_NUMPY,
        )
        # Nulls beyond the two None fields are values the template must print.
        if payload.count(b"null") != (output is None) + (error is None):
            return self._invocation_template(r)
        return payload

    def _invocation_template(self, r: EcmInvocation) -> bytes:
        outcome = _OUTCOMES.get(r.outcome)
        if outcome is None:
            outcome = _OUTCOMES[Outcome(r.outcome)]  # ValueError for anything else
        return _INVOCATION_TEMPLATE % (
            r.episode,
            r.step,
            self.name_json(r.ecm),
            r.version,
            vector_json(r.input_state),
            b"null" if r.output is None else vector_json(r.output),
            _format_float(r.duration_s),
            outcome,
            b"null" if r.error is None else orjson.dumps(str(r.error)),
        )

    def rows(self, rows: Sequence[tuple[bool, EnvStepRow | InvocationRow]]) -> list[bytes | Invalid]:
        """The payloads of a batch of rows, in order: env step rows (``True``) and invocation
        rows (``False``); a row that does not encode gets its :class:`Invalid` instead.

        One :func:`orjson.dumps` call prints every vector of the batch (a vector shared by rows,
        such as one step's ``next_obs`` as the next step's ``obs`` and an ECM's input, once),
        and each payload is spliced from those texts, the bytes :meth:`env_step` and
        :meth:`invocation` give the rows' records; what they would send to the template path
        goes there too. The splicing runs in C (``csrc/rows.c``) where it is built;
        :meth:`rows_in_python` is its specification.
        """
        if _native is None or not self._kernel:
            return self.rows_in_python(rows)
        batch = rows if type(rows) is list else list(rows)
        payloads: list[Any] = _native.encode_rows(batch, self.name_json)
        for i, payload in enumerate(payloads):
            if payload is None:
                payloads[i] = self.record_path(*batch[i])
        return payloads

    def rows_in_python(self, rows: Sequence[tuple[bool, EnvStepRow | InvocationRow]]) -> list[bytes | Invalid]:
        """:meth:`rows` without the C splicer: the same payloads, several µs more per row."""
        vectors: list[Any] = []
        observations: dict[int, int] = {}  # id of an observation vector -> its index in vectors
        runtime: dict[int, int] = {}  # id of a runtime (exact) vector -> its index
        # The tables key by id: hold each keyed vector, or a freed one (an arm's property makes
        # a new tuple per read) could hand its id, and so its text, to the next.
        keyed: list[Any] = []
        add = vectors.append

        def slotter(slots: dict[int, int], convert: Any) -> Any:
            def slot(v: Any) -> int:
                i = slots.get(id(v))
                if i is None:
                    converted = convert(v)  # before the entry: a vector that fails must fail every row it is in
                    keyed.append(v)
                    i = slots[id(v)] = len(vectors)
                    add(converted)
                return i  # type: ignore[no-any-return]

            return slot

        observation = slotter(observations, float32_array)
        exact = slotter(runtime, _exact_or_float32)

        plans: list[tuple[Any, ...] | None] = []
        for is_step, row in rows:
            try:
                episode, step, ecm, version = row[:4]
                if (
                    type(episode) is not int
                    or type(step) is not int
                    or type(version) is not int
                    or type(ecm) is not str
                    or (episode | step | version) >> 63  # negative or beyond int64: the record path decides
                ):
                    plans.append(None)
                    continue
                if is_step:
                    obs, action, reward, next_obs, terminated, truncated, success, arms = row[4:]
                    keys = []
                    for arm in arms:
                        keys.append(exact(arm.eef_pos))
                        keys.append(exact(arm.eef_force))
                    o, a, n = observation(obs), exact(action), observation(next_obs)
                    r = len(vectors)
                    add((float(reward),))
                    slots = (o, a, r, n, *keys)
                    flags = (_BOOLS[bool(terminated)], _BOOLS[bool(truncated)], _BOOLS[bool(success)])
                    plans.append((slots, slots, episode, step, self.name_json(ecm), version, flags))
                else:
                    inputs, selection, output, duration, outcome, error = row[4:]
                    outcome_text = _OUTCOMES.get(outcome)
                    if outcome_text is None or (
                        selection is not None and (type(selection) is not tuple or not _is_float32_vector(inputs))
                    ):
                        plans.append(None)
                        continue
                    error_text = b"null" if error is None else _error_json(error)
                    i = observation(inputs)
                    out = None if output is None else exact(output)
                    d = len(vectors)
                    add((float(duration),))
                    slots = (i, d) if out is None else (i, d, out)
                    # A selection's values are checked for null in its own text, not its vector's.
                    checked = slots if selection is None else slots[1:]
                    texts = (outcome_text, error_text, selection)
                    plans.append((slots, checked, episode, step, self.name_json(ecm), version, texts))
            except (TypeError, ValueError, OverflowError, AttributeError):
                plans.append(None)

        text = orjson.dumps(vectors, option=_NUMPY)
        # Every vector is flat, so "],[" only ever separates two of them.
        parts = text[2:-2].split(b"],[") if vectors else []
        with_null = {i for i, part in enumerate(parts) if b"null" in part} if b"null" in text else None
        payloads: list[bytes | Invalid] = []
        for plan, (is_step, row) in zip(plans, rows, strict=True):
            if plan is None or (with_null and not with_null.isdisjoint(plan[1])):
                payloads.append(self.record_path(is_step, row))
                continue
            slots, _, episode, step, name, version, texts = plan
            if is_step:
                o, a, r, n, *keys = slots
                payloads.append(
                    _ENV_STEP_ROW_TEMPLATE
                    % (
                        episode,
                        step,
                        name,
                        version,
                        parts[o],
                        parts[a],
                        parts[r],
                        parts[n],
                        *texts,
                        _key_state_template(len(keys) // 2) % tuple(parts[k] for k in keys),
                    )
                )
            else:
                outcome_text, error_text, selection = texts
                inputs = parts[slots[0]] if selection is None else _selected_text(parts[slots[0]], selection)
                if inputs is None:
                    payloads.append(self.record_path(is_step, row))
                    continue
                output = b"null" if len(slots) == 2 else b"[" + parts[slots[2]] + b"]"
                payloads.append(
                    _INVOCATION_ROW_TEMPLATE
                    % (episode, step, name, version, inputs, output, parts[slots[1]], outcome_text, error_text)
                )
        return payloads

    def record_path(self, is_step: bool, row: Any) -> bytes | Invalid:
        """The payload of a row's record (what :meth:`rows` gives a row it cannot splice), or its
        :class:`Invalid`."""
        try:
            return self.env_step(env_step_of(row)) if is_step else self.invocation(invocation_of(row))
        except Invalid as exc:
            return exc

    def _intervention(self, r: Intervention) -> bytes:
        return _INTERVENTION_TEMPLATE % (
            r.episode,
            r.step,
            self.name_json(r.constraint),
            vector_json(r.original_action),
            b"null" if r.result_action is None else vector_json(r.result_action),
            orjson.dumps(str(r.reason)),
            _BOOLS[bool(r.enforced)],
        )


def _is_float32_vector(values: Any) -> bool:
    return type(values) is np.ndarray and values.dtype == _FLOAT32 and values.ndim == 1 and values.flags.c_contiguous


def _selected_text(vector_text: bytes, selection: tuple[Any, ...]) -> bytes | None:
    """The text of the vector's values at the positions ``selection``, cut from the vector's
    text; None where the record path decides (a position that is not an int in the vector, or a
    null among the values)."""
    elements = vector_text.split(b",") if vector_text else []
    if not all(type(k) is int and 0 <= k < len(elements) for k in selection):
        return None
    text = b",".join([elements[k] for k in selection])
    return None if b"n" in text else text


_KEY_STATE_TEMPLATES: dict[int, bytes] = {}


def _key_state_template(arms: int) -> bytes:
    """``"arm0_eef_pos":[%b],"arm0_eef_force":[%b],...`` for ``arms`` arms (cached)."""
    template = _KEY_STATE_TEMPLATES.get(arms)
    if template is None:
        names = [orjson.dumps(name) for i in range(arms) for name in arm_keys(i)]
        template = _KEY_STATE_TEMPLATES[arms] = b",".join(name + b":[%b]" for name in names)
    return template


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    return value


def encode_dict(d: dict[str, Any]) -> bytes:
    """Compact strict JSON of ``d`` (the generic path); non-finite floats become ``null``."""
    try:
        return _ENCODER.encode(d).encode()
    except ValueError:
        return _ENCODER.encode(_finite_or_none(d)).encode()


def encode(record: TraceRecord) -> bytes:
    """The JSON payload of any trace record (with a fresh :class:`RecordEncoder`).

    Raises:
        Invalid: a field has a type JSON cannot carry.
    """
    return RecordEncoder().encode(record)


def decode(topic: str, data: bytes | bytearray | memoryview) -> TraceRecord:
    """The record of ``topic`` that ``data`` encodes.

    Raises:
        Invalid: unknown topic.
        Corrupt: the payload is not JSON or lacks a field the record needs.
    """
    cls = record_type(topic)
    try:
        return cls.from_dict(json.loads(bytes(data)))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise Corrupt(
            f"message on {topic} does not decode as {cls.__name__}: {type(exc).__name__}: {exc}",
            details={"topic": topic},
        ) from None
