"""One evaluation call's seeds split across runtime workers (issue 19), merged back in seed order.

The bookkeeping (:mod:`capevo.runtime.fanout`) is checked on its own first, one test per
invariant. Then real worker processes (``capevo runtime serve``, each a fresh interpreter)
against a real registry server process, over loopback Zenoh with scouting off: the split is
the one :func:`split` gives, and its merged outcomes equal a one-worker run on the same
seeds; each part's trace comes back with its outcomes; inline candidate artifacts run on the
workers, sandboxed, and change nothing after their call; a worker SIGKILLed (or SIGTERMed) in
the middle of a call, or one whose query ends unanswered, loses no seed and counts none twice;
the same through a plain Zenoh router and under the registry's access control.
"""

from __future__ import annotations

import hashlib
import random
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from procs import ServerProcess, start_server
from runtime_support import Proc, publish_pick, start_worker

from capevo.errors import CapevoError, Forbidden, Invalid, Unavailable
from capevo.records import Origin
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.fanout import SeedLedger, split
from capevo.runtime.remote_evaluator import RemoteEvaluator
from capevo.runtime.traces import TraceReader
from capevo.runtime.worker_protocol import EvaluateRequest

HORIZON = "20"
# A reach that holds still with the gripper open: with it no episode gets near the can.
HOLD = b"""
PARAMS = {}
def act(obs, params):
    return [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]
"""


def outcome(seed: int, *, success: bool = False) -> EpisodeOutcome:
    return EpisodeOutcome(
        seed=seed,
        success=success,
        reward=0.0,
        steps=1,
        duration_s=0.0,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={},
    )


# --- the bookkeeping, without processes -------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(min_value=0, max_value=40),
    workers=st.lists(st.text("abcdef", min_size=1, max_size=3), min_size=1, max_size=6),
    order=st.randoms(use_true_random=False),
)
def test_split_depends_only_on_the_worker_set_and_covers_every_index_once(
    n: int, workers: list[str], order: random.Random
) -> None:
    """Invariant 1."""
    parts = split(range(n), workers)
    shuffled = list(workers) * 2
    order.shuffle(shuffled)
    assert split(range(n), shuffled) == parts
    assert [w for w, _ in parts] == sorted(set(workers))[: len(parts)]
    flat = [i for _, idx in parts for i in idx]
    assert flat == list(range(n))  # contiguous runs in order: each index exactly once
    sizes = [len(idx) for _, idx in parts]
    assert all(sizes) and (not sizes or max(sizes) - min(sizes) <= 1)
    assert sizes == sorted(sizes, reverse=True)


def test_split_needs_a_worker() -> None:
    with pytest.raises(Invalid) as err:
        split([0, 1], [])
    assert err.value.code.value == "invalid" and err.value.message == "split: no worker to run the seeds on"


def test_a_late_reply_of_a_failed_part_never_counts_a_seed_twice() -> None:
    """Invariants 2, 4 and 6: a worker taken for dead answers after its seeds were re-run."""
    seeds = [10, 11, 12, 13, 14]
    ledger = SeedLedger(seeds)
    a, b = ledger.dispatch(["w-b", "w-a"])
    assert (a.worker_id, a.seeds, b.worker_id, b.seeds) == ("w-a", (10, 11, 12), "w-b", (13, 14))
    assert ledger.fail(b.part_id) == (3, 4)
    assert ledger.pool == (3, 4)
    (again,) = ledger.dispatch(["w-a"])
    assert again.seeds == (13, 14) and ledger.pool == ()
    assert [p.part_id for p in ledger.in_flight()] == [a.part_id, again.part_id]  # no index on two parts
    with pytest.raises(Invalid):
        ledger.merged()  # invariant 4: not before every seed is in
    assert ledger.complete(a.part_id, [outcome(s) for s in a.seeds]) == 3
    assert ledger.complete(b.part_id, [outcome(s, success=True) for s in b.seeds]) == 2  # the late one fills
    assert ledger.complete(again.part_id, [outcome(s) for s in again.seeds]) == 0
    assert ledger.dropped == 2 and ledger.failed_parts == 1 and ledger.done
    merged = ledger.merged()
    assert [o.seed for o in merged] == seeds
    assert [o.success for o in merged] == [False, False, False, True, True]


def test_a_reply_for_other_seeds_is_refused_and_fails_its_part() -> None:
    """Invariant 3."""
    ledger = SeedLedger([1, 2, 2])
    (part,) = ledger.dispatch(["w"])
    with pytest.raises(CapevoError) as err:
        ledger.complete(part.part_id, [outcome(1), outcome(2), outcome(3)])
    assert err.value.message == "runtime worker w returned outcomes for seeds [1, 2, 3], asked for [1, 2, 2]"
    assert ledger.pool == (0, 1, 2) and not ledger.in_flight()
    with pytest.raises(CapevoError):
        ledger.complete(part.part_id, [outcome(1)])


def test_a_seed_is_dispatched_at_most_max_attempts_times() -> None:
    """Invariant 5."""
    ledger = SeedLedger([7, 8], max_attempts=2)
    for _ in range(2):
        for part in ledger.dispatch(["w-a", "w-b"]):
            ledger.fail(part.part_id)
    assert ledger.attempts(0) == ledger.attempts(1) == 2
    with pytest.raises(Unavailable) as err:
        ledger.dispatch(["w-a"])
    assert err.value.code.value == "unavailable"
    assert err.value.message.startswith("seeds [7, 8] were dispatched 2 times")
    with pytest.raises(Invalid):
        SeedLedger([1], max_attempts=0)


def test_inline_artifacts_round_trip_and_bad_ones_name_their_field() -> None:
    request = EvaluateRequest(
        task="pick",
        versions={"pick.lift": 0},
        seeds=(3, 1),
        overrides={"pick.reach": HOLD, "pick.lift": bytes(range(256))},
        override_origin=Origin.CLONE,
        traces=True,
    )
    assert EvaluateRequest.from_json(request.to_json()) == request
    cases = [
        (b'{"task": "T1", "seeds": [0], "overrides": {"pick.reach": "%%%"}}', "overrides", "is not base64"),
        (b'{"task": "T1", "seeds": [0], "overrides": {"pick.reach": 3}}', "overrides", "base64 text"),
        (b'{"task": "T1", "seeds": [0], "overrides": {"place.drop": "eA=="}}', "overrides", "not an ECM of task"),
        (b'{"task": "T1", "seeds": [0], "overrides": {"pick.reach": ""}}', "overrides", "non-empty bytes"),
        (b'{"task": "T1", "seeds": [0], "override_origin": "alien"}', "override_origin", "unknown override_origin"),
        (b'{"task": "T1", "seeds": [0], "traces": 1}', "traces", "traces must be true or false"),
    ]
    for payload, field, text in cases:
        with pytest.raises(Invalid) as err:
            EvaluateRequest.from_json(payload)
        assert err.value.details["field"] == field and text in err.value.message, (payload, err.value.message)


# --- real workers -----------------------------------------------------------------------------


@dataclass
class Cluster:
    endpoint: str
    registry: ServerProcess
    workers: dict[str, Proc]
    root: Path

    def start(self, worker_id: str, *, traces: bool = True, login: Sequence[str] = ()) -> Proc:
        keep = ["--trace-dir", str(self.root / worker_id), "--trace-compression", "none"] if traces else []
        proc = start_worker(
            self.endpoint,
            task="T1",
            log_path=self.root / f"{worker_id}.log",
            extra=[
                "--worker-id",
                worker_id,
                "--idle",
                "--horizon",
                HORIZON,
                *keep,
                *login,
                "--cache-dir",
                str(self.root / worker_id / "cache"),
            ],
        )
        self.workers[worker_id] = proc
        return proc

    def ran_on(self, o: EpisodeOutcome) -> str:
        """Which worker ran an episode: its trace file lies under that worker's trace directory."""
        assert o.trace_path is not None
        return Path(o.trace_path).relative_to(self.root).parts[0]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    root = tmp_path_factory.mktemp("fanout")
    registry = start_server(root / "registry")
    with registry.client(actor="tester") as client:
        publish_pick(client)
    c = Cluster(endpoint=registry.endpoint, registry=registry, workers={}, root=root)
    try:
        c.start("w-a")
        c.start("w-b")
        yield c
    finally:
        codes = {w: p.terminate() for w, p in c.workers.items() if p.running()}
        registry.stop()
    assert all(code == 0 for code in codes.values()), {w: c.workers[w].log()[-2000:] for w in codes}


def same_episodes(a: list[EpisodeOutcome], b: list[EpisodeOutcome]) -> None:
    assert [(o.seed, o.success, o.reward, o.steps) for o in a] == [(o.seed, o.success, o.reward, o.steps) for o in b]


def discovered(evaluator: RemoteEvaluator, expected: Sequence[str], timeout: float = 60.0) -> list[str]:
    """The task's live workers once ``expected`` are all among them (or whatever is live at the deadline).

    A worker prints ``ready`` once it has declared its liveliness token; the router (or a peer)
    learns of the token a moment later, so a discovery issued right after ``ready`` can miss it.
    The split depends on who is live, so tests that assert on it wait for discovery first.
    """
    deadline = time.monotonic() + timeout
    while True:
        live = evaluator.live_workers("T1")
        if set(expected) <= set(live) or time.monotonic() > deadline:
            return live
        time.sleep(0.2)


@pytest.mark.slow
@pytest.mark.zenoh
def test_the_split_is_deterministic_and_merges_to_a_one_worker_run(cluster: Cluster) -> None:
    seeds = [5, 3, 8, 1, 9]
    with RemoteEvaluator(cluster.endpoint, timeout=240) as evaluator:
        assert discovered(evaluator, ["w-a", "w-b"]) == ["w-a", "w-b"]
        first = evaluator.evaluate("T1", {}, seeds)
        assert evaluator.last_call == {"parts": 2, "failed_parts": 0, "dropped": 0, "workers": ["w-a", "w-b"]}
        second = evaluator.evaluate("T1", {}, seeds)
    with RemoteEvaluator(cluster.endpoint, worker_id="w-a", timeout=240) as alone:
        one = alone.evaluate("T1", {}, seeds)
    assert [o.seed for o in first] == seeds
    # the split is split()'s: the first three seeds on w-a, the last two on w-b, both times
    expected = {i: w for w, idx in split(range(len(seeds)), ["w-b", "w-a"]) for i in idx}
    assert [cluster.ran_on(o) for o in first] == [expected[i] for i in range(len(seeds))]
    assert [cluster.ran_on(o) for o in second] == [cluster.ran_on(o) for o in first]
    assert {cluster.ran_on(o) for o in one} == {"w-a"}
    same_episodes(first, one)
    same_episodes(second, one)
    assert all(0 < o.steps <= int(HORIZON) for o in one)


@pytest.mark.slow
@pytest.mark.zenoh
def test_each_part_s_trace_comes_back_with_its_outcomes(cluster: Cluster, tmp_path: Path) -> None:
    """Learners read the episodes of workers on other hosts from local copies (no shared disk)."""
    seeds = [31, 32, 33]
    with RemoteEvaluator(cluster.endpoint, timeout=240, trace_dir=tmp_path) as evaluator:
        outcomes = evaluator.evaluate("T1", {}, seeds)
    local = sorted({str(o.trace_path) for o in outcomes})
    assert [Path(p).parent for p in local] == [tmp_path, tmp_path]
    for path in local:
        worker, name = Path(path).name[:3], Path(path).name[4:]  # "w-a-" + the worker's file name
        original = cluster.root / worker / "evaluations" / name
        assert Path(path).read_bytes() == original.read_bytes()
        with TraceReader(path) as reader:
            ran = [e.seed for e in reader.episode_summaries()]
        assert ran == [o.seed for o in outcomes if o.trace_path == path]
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
@pytest.mark.zenoh
def test_inline_candidates_run_on_the_workers_sandboxed_and_only_for_their_call(cluster: Cluster) -> None:
    seeds = [2, 4]
    with RemoteEvaluator(cluster.endpoint, timeout=240) as evaluator:
        before = evaluator.evaluate("T1", {}, seeds)
        # a manual-origin override would run shipped bytes in the worker's own process
        with pytest.raises(Forbidden) as err:
            evaluator.evaluate("T1", {}, seeds, overrides={"pick.reach": HOLD})
        assert err.value.code.value == "forbidden" and "inline code runs only in the sandbox" in err.value.message
        with pytest.raises(Invalid) as bad:
            evaluator.evaluate("T1", {}, seeds, overrides={"place.drop": b"x"})
        assert bad.value.message.startswith("override 'place.drop' is not an ECM of task 'pick'")
        held = evaluator.evaluate("T1", {}, seeds, overrides={"pick.reach": HOLD}, override_origin=Origin.CLONE)
        after = evaluator.evaluate("T1", {}, seeds)
    assert [o.seed for o in held] == seeds
    assert {cluster.ran_on(o) for o in held} == {"w-a", "w-b"}
    # reported at the version the override stands in for
    assert all(dict(o.capability_set) == {"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0} for o in held)
    # the override is what ran: an arm that holds still earns other rewards than one that reaches
    assert [o.reward for o in held] != [o.reward for o in before]
    same_episodes(after, before)  # worker invariant 6: nothing of the override stays behind
    cached = {p.name for p in cluster.root.glob("w-*/cache/*/*")}
    assert cached, "the workers cache the registry's artifacts"
    assert hashlib.sha256(HOLD).hexdigest() not in cached


@pytest.mark.slow
@pytest.mark.zenoh
@pytest.mark.parametrize(
    ("victim_id", "how"),
    [
        ("w-c", "sigkill"),  # dies silently: its liveliness token goes (or its query ends unanswered)
        ("w-d", "sigterm"),  # shuts down cleanly: it refuses the running part with `unavailable`
    ],
)
def test_a_worker_killed_mid_call_loses_no_seed_and_counts_none_twice(
    cluster: Cluster, victim_id: str, how: str
) -> None:
    seeds = [11, 12, 13, 14, 15, 16]
    with RemoteEvaluator(cluster.endpoint, worker_id="w-a", timeout=300) as alone:
        reference = alone.evaluate("T1", {}, seeds)
    victim = cluster.start(victim_id)
    with RemoteEvaluator(cluster.endpoint, timeout=300) as watcher:
        assert victim_id in discovered(watcher, [victim_id]), victim.log()[-3000:]
    evaluations = cluster.root / victim_id / "evaluations"
    result: dict[str, object] = {}

    def call() -> None:
        with RemoteEvaluator(cluster.endpoint, timeout=300) as evaluator:
            try:
                result["outcomes"] = evaluator.evaluate("T1", {}, seeds)
            except BaseException as exc:  # re-raised on the test's thread below
                result["error"] = exc
            result["last_call"] = dict(evaluator.last_call)

    thread = threading.Thread(target=call)
    thread.start()
    # w-c opens its evaluation's trace file when its part starts: kill it in the middle of the part
    deadline = time.monotonic() + 120
    while not list(evaluations.glob("*.mcap")) and time.monotonic() < deadline and thread.is_alive():
        time.sleep(0.05)
    assert list(evaluations.glob("*.mcap")), victim.log()[-3000:]
    if how == "sigkill":
        victim.kill()
    else:
        assert victim.terminate() == 0, victim.log()[-3000:]
    thread.join(300)
    assert not thread.is_alive()
    if "error" in result:
        raise result["error"]  # type: ignore[misc]
    outcomes = result["outcomes"]
    assert isinstance(outcomes, list)
    assert [o.seed for o in outcomes] == seeds  # one outcome per seed, in order
    same_episodes(outcomes, reference)
    # the victim's part (the last two seeds: its id sorts last of three) was re-run by the survivors
    assert {cluster.ran_on(o) for o in outcomes[4:]} <= {"w-a", "w-b"}
    last = result["last_call"]
    assert isinstance(last, dict) and last["failed_parts"] >= 1 and victim_id in last["workers"]


# A worker that announces itself like a real one and then drops every evaluate query unanswered,
# as a worker whose process dies with the query does (the query ends without a reply).
_SILENT_WORKER = """
import sys, zenoh
from capevo.registry.zconfig import client_config
from capevo.runtime.worker_protocol import RuntimeKeys
endpoint, worker_id = sys.argv[1], sys.argv[2]
keys = RuntimeKeys("capevo")
session = zenoh.open(client_config(connect=[endpoint]))
def drop(query):
    with query:
        print("DROPPED", flush=True)
queryable = session.declare_queryable(keys.evaluate(worker_id), drop)
tokens = [session.liveliness().declare_token(k) for k in (keys.alive(worker_id), keys.serves(worker_id, "T1"))]
print("READY", flush=True)
sys.stdin.read()
for t in tokens:
    t.undeclare()
queryable.undeclare()
session.close()
"""


@pytest.mark.slow
@pytest.mark.zenoh
def test_a_part_whose_query_ends_unanswered_is_rerun_elsewhere(cluster: Cluster) -> None:
    seeds = [51, 52, 53, 54]
    with RemoteEvaluator(cluster.endpoint, worker_id="w-a", timeout=240) as alone:
        reference = alone.evaluate("T1", {}, seeds)
    silent = subprocess.Popen(
        [sys.executable, "-c", _SILENT_WORKER, cluster.endpoint, "w-0-silent"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert silent.stdout is not None and silent.stdout.readline().strip() == "READY"
        with RemoteEvaluator(cluster.endpoint, timeout=240) as evaluator:
            # it sorts first: it gets the first part
            assert discovered(evaluator, ["w-0-silent", "w-a", "w-b"])[0] == "w-0-silent"
            outcomes = evaluator.evaluate("T1", {}, seeds)
            last = dict(evaluator.last_call)
        assert silent.stdout.readline().strip() == "DROPPED"
    finally:
        assert silent.stdin is not None
        silent.stdin.close()
        silent.wait(timeout=30)
        silent.stdout.close()  # type: ignore[union-attr]
    assert [o.seed for o in outcomes] == seeds
    same_episodes(outcomes, reference)
    assert last["failed_parts"] == 1 and last["dropped"] == 0 and "w-0-silent" in last["workers"]
    assert {cluster.ran_on(o) for o in outcomes} <= {"w-a", "w-b"}


@pytest.mark.slow
@pytest.mark.zenoh
def test_workers_elsewhere_join_through_a_router(tmp_path: Path) -> None:
    """docs/multi-host.md's layout on one machine: a plain Zenoh router (zenohd's stand-in) in
    the middle, the registry joined to it with ``--connect``, the workers and the evaluator its
    clients; no process connects to the registry directly."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "registry"))
    from zenoh_fixtures import hub_router

    with hub_router("a1b2c3d4e5f60718") as hub:
        registry = start_server(tmp_path / "registry", connect=[hub])
        c = Cluster(endpoint=hub, registry=registry, workers={}, root=tmp_path)
        try:
            with registry.client(actor="tester") as client:
                publish_pick(client)
            # workers that keep no traces of their own: they still send each call's trace back
            c.start("w-x", traces=False)
            c.start("w-y", traces=False)
            with RemoteEvaluator(hub, timeout=240, trace_dir=tmp_path / "here") as evaluator:
                assert discovered(evaluator, ["w-x", "w-y"]) == ["w-x", "w-y"]
                outcomes = evaluator.evaluate("T1", {}, [21, 22, 23])
                assert evaluator.last_call["workers"] == ["w-x", "w-y"]
            with RemoteEvaluator(hub, worker_id="w-y", timeout=240) as alone:
                untraced = alone.evaluate("T1", {}, [21, 22, 23])
            same_episodes(outcomes, untraced)
            assert all(o.trace_path is None for o in untraced)
            assert [Path(str(o.trace_path)).name.split("-")[:2] for o in outcomes] == [["w", "x"]] * 2 + [["w", "y"]]
            for o in outcomes:
                with TraceReader(str(o.trace_path)) as reader:
                    assert o.seed in [e.seed for e in reader.episode_summaries()]
            assert not list(tmp_path.glob("w-*/evaluations"))
        finally:
            codes = [p.terminate() for p in c.workers.values()]
            registry.stop()
        assert codes == [0, 0]


SECURED = """
users:
  olga: {password: "olga-secret", roles: [operator]}
  wendy: {password: "wendy-secret", roles: [runtime]}
  wally: {password: "wally-secret", roles: [runtime]}
  rita: {password: "rita-secret", roles: [reader]}
"""


@pytest.mark.slow
@pytest.mark.zenoh
def test_the_split_works_under_access_control(tmp_path: Path) -> None:
    """Workers log in with the runtime role, the evaluator with the reader role: the liveliness
    tokens, the parts' queries and their replies (trace attachments included) all pass the
    registry's access control."""
    (tmp_path / "registry.yaml").write_text(SECURED)
    registry = start_server(tmp_path / "registry", config=tmp_path / "registry.yaml")
    assert registry.info["secured"] is True
    c = Cluster(endpoint=registry.endpoint, registry=registry, workers={}, root=tmp_path)
    try:
        with registry.client(user="olga", password="olga-secret") as client:
            publish_pick(client)
        c.start("w-1", login=["--user", "wendy", "--password", "wendy-secret"])
        c.start("w-2", login=["--user", "wally", "--password", "wally-secret"])
        with RemoteEvaluator(
            registry.endpoint, user="rita", password="rita-secret", timeout=240, trace_dir=tmp_path / "here"
        ) as evaluator:
            assert discovered(evaluator, ["w-1", "w-2"]) == ["w-1", "w-2"]
            outcomes = evaluator.evaluate("T1", {}, [41, 42])
            assert evaluator.last_call["workers"] == ["w-1", "w-2"]
        assert [o.seed for o in outcomes] == [41, 42]
        assert [Path(str(o.trace_path)).parent for o in outcomes] == [tmp_path / "here"] * 2
    finally:
        codes = [p.terminate() for p in c.workers.values()]
        registry.stop()
    assert codes == [0, 0]
