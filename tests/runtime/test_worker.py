"""The runtime worker as a real process against a real registry server process over Zenoh.

Loopback TCP, multicast scouting off (the registry's and the worker's Zenoh configs keep it
off). Covers the worker's invariants: swaps only between episodes (1), one reply per evaluate
query, even for garbage (2), the adoption key naming the running versions (3), episodes go on
without the registry (4), one capability set per trace file (5).
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from procs import ServerProcess, start_server
from runtime_support import LIFT, Proc, chunk_compressions, publish, publish_pick, start_worker

from capevo.errors import Invalid, Unavailable, error_from_payload
from capevo.registry.client import Client
from capevo.registry.zconfig import client_config
from capevo.runtime.evaluation import Evaluator
from capevo.runtime.gate import SeedPlan
from capevo.runtime.remote_evaluator import RemoteEvaluator, list_workers
from capevo.runtime.tasks import task_ids, task_names
from capevo.runtime.traces import TraceReader
from capevo.runtime.worker_protocol import Adoption, RuntimeKeys

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

WORKER_ID = "w-test"
KEYS = RuntimeKeys("capevo")
SLOW_LIFT = LIFT.replace('"speed": 1.0', '"speed": 0.5')
VALID_TASKS = {*task_names(), *task_ids()}


@dataclass
class Running:
    endpoint: str
    registry: ServerProcess
    worker: Proc
    root: Path


def is_episode(line: dict) -> bool:
    return line.get("event") == "episode"


def start_pick_registry(root: Path) -> ServerProcess:
    """A registry server process under ``root`` with T1's reach, grasp and lift published and promoted."""
    registry = start_server(root / "registry")
    with registry.client(actor="tester") as client:
        publish_pick(client)
    return registry


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    root = tmp_path_factory.mktemp("worker")
    registry = start_pick_registry(root)
    endpoint = registry.endpoint
    worker = start_worker(
        endpoint,
        task="T1",
        log_path=root / "worker.log",
        extra=[
            "--worker-id",
            WORKER_ID,
            "--horizon",
            "30",
            "--trace-dir",
            str(root / "traces"),
            "--trace-compression",
            "none",
            "--cache-dir",
            str(root / "cache"),
        ],
    )
    try:
        yield Running(endpoint=endpoint, registry=registry, worker=worker, root=root)
    finally:
        assert worker.terminate() == 0, worker.log()[-3000:]
        registry.stop()


def adoption(endpoint: str) -> Adoption:
    (found,) = [a for a in list_workers(endpoint) if a.worker_id == WORKER_ID]
    return found


def test_worker_runs_adopts_swaps_and_evaluates(running: Running) -> None:
    worker, endpoint = running.worker, running.endpoint
    ready = worker.lines[0]
    assert ready["event"] == "ready" and ready["task"] == "pick"
    assert ready["keys"]["adopted"] == f"capevo/runtime/{WORKER_ID}/adopted"
    first = worker.read_until(is_episode, 60)
    assert first["versions"] == {"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0}

    # adoption key and liveliness token
    with Client([endpoint]) as client:
        revision = client.capability_set().revision
    adopted = adoption(endpoint)
    assert adopted.task == "pick" and adopted.revision == revision
    assert dict(adopted.versions) == first["versions"] and adopted.registry_connected
    with zenoh.open(client_config(connect=[endpoint])) as session:
        alive = [str(r.ok.key_expr) for r in session.liveliness().get(KEYS.alive_all(), timeout=3) if r.ok]
    assert KEYS.alive(WORKER_ID) in alive

    # promote -> hot swap at the next episode boundary
    with Client([endpoint], actor="tester") as client:
        new = publish(client, "pick.lift", SLOW_LIFT)
    swap = worker.read_until(lambda x: x.get("event") == "swap", 30)
    assert (swap["name"], swap["from_version"], swap["to_version"], swap["applied"]) == (
        "pick.lift",
        0,
        new.version,
        True,
    )
    after = worker.read_until(lambda x: is_episode(x) and x["versions"]["pick.lift"] == new.version, 30)
    assert after["revision"] >= revision + 1
    assert adoption(endpoint).versions["pick.lift"] == new.version

    # evaluation through the shared task key, with a pinned version
    with RemoteEvaluator(endpoint, timeout=120) as evaluator:
        assert isinstance(evaluator, Evaluator)
        outcomes = evaluator.evaluate("T1", {"pick.lift": 0}, [4, 2])
    assert [o.seed for o in outcomes] == [4, 2]
    assert all(o.capability_set["pick.lift"] == 0 and 0 < o.steps <= 30 for o in outcomes)
    trace = outcomes[0].trace_path
    assert trace is not None and Path(trace).parent == running.root / "traces" / "evaluations"
    with TraceReader(trace) as reader:
        assert [s.seed for s in reader.episode_summaries()] == [4, 2]
    assert chunk_compressions(Path(trace)) == {""}  # --trace-compression none
    evaluated = worker.read_until(lambda x: x.get("event") == "evaluated", 10)
    assert evaluated["seeds"] == 2

    # a worker refuses another task's evaluation, with the worker's error class and code
    with RemoteEvaluator(endpoint, worker_id=WORKER_ID, timeout=30) as evaluator, pytest.raises(Invalid) as err:
        evaluator.evaluate("T2", {}, [0])
    assert err.value.message == f"runtime worker {WORKER_ID} runs task 'pick', not 'place'"

    # rollback -> swap back
    with Client([endpoint], actor="tester") as client:
        client.rollback("pick.lift", reason="test")
    worker.read_until(lambda x: x.get("event") == "swap" and x["to_version"] == 0, 30)
    worker.read_until(lambda x: is_episode(x) and x["versions"]["pick.lift"] == 0, 30)

    # every trace file holds one capability set
    files = sorted((running.root / "traces").glob(f"{WORKER_ID}-*.mcap"))
    assert len(files) >= 2
    for path in files[:-1]:  # the last one is still being written
        with TraceReader(path) as reader:
            sets = {tuple(sorted(s.capability_set.items())) for s in reader.episode_summaries()}
            assert len(sets) == 1
            assert dict(next(iter(sets))) == dict(reader.metadata().capability_set.active)
        assert chunk_compressions(path) == {""}


def cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "capevo.cli.runtime", *args], capture_output=True, text=True, timeout=timeout
    )


def test_cli_lists_workers_and_evaluates_through_them(running: Running, tmp_path: Path) -> None:
    listed = cli("list", "--connect", running.endpoint, "--json")
    assert listed.returncode == 0, listed.stderr
    (mine,) = [w for w in json.loads(listed.stdout) if w["worker_id"] == WORKER_ID]
    assert mine["task"] == "pick" and set(mine["versions"]) == {"pick.reach", "pick.grasp", "pick.lift"}
    evaluated = cli(
        "evaluate",
        "--connect",
        running.endpoint,
        "--task",
        "pick",
        "--seeds",
        "7",
        "--version",
        "pick.lift=0",
        "--trace-dir",
        str(tmp_path / "traces"),
        "--json",
    )
    assert evaluated.returncode == 0, evaluated.stderr
    (outcome,) = json.loads(evaluated.stdout)
    assert outcome["seed"] == 7 and outcome["capability_set"]["pick.lift"] == 0
    # the worker's part came back over Zenoh into --trace-dir, and it holds this episode
    trace = Path(outcome["trace_path"])
    assert trace.parent == tmp_path / "traces" and trace.name.startswith(WORKER_ID)
    with TraceReader(trace) as reader:
        assert [(s.seed, s.success) for s in reader.episode_summaries()] == [(7, outcome["success"])]
    refused = cli("evaluate", "--connect", running.endpoint, "--task", "pick", "--version", "pick.lift=99")
    assert refused.returncode == 4, refused.stderr  # not_found, raised by the worker's registry lookup
    assert refused.stderr.startswith("error [not_found]: ")


def test_cli_gates_a_candidate_on_the_workers(running: Running) -> None:
    """``capevo runtime gate --connect``: the pair runs on the task's runtime workers, the decision
    and its evidence go to the registry server."""
    with Client([running.endpoint], actor="tester") as client:
        candidate = publish(client, "pick.lift", LIFT, promote=False)
    gated = cli(
        "gate",
        "pick.lift",
        str(candidate.version),
        "--connect",
        running.endpoint,
        "--preset",
        "tiny",
        "--round",
        "0",
        "--json",
        timeout=300,
    )
    assert gated.returncode == 0, gated.stderr
    decision = json.loads(gated.stdout)
    assert (decision["name"], decision["candidate_version"]) == ("pick.lift", candidate.version)
    assert decision["seeds"] == SeedPlan(base_seed=0).gate(4, round=0)  # tiny: N = 4, batch 0
    with Client([running.endpoint]) as client:
        record = client.get_version("pick.lift", candidate.version)
    assert record.gate_evidence and record.state.value == ("active" if decision["promoted"] else "rejected")


def test_no_worker_for_a_task_is_unavailable(running: Running) -> None:
    with RemoteEvaluator(running.endpoint, timeout=5) as evaluator, pytest.raises(Unavailable) as err:
        evaluator.evaluate("T2", {}, [0])
    assert err.value.code.value == "unavailable"
    assert "no runtime worker of task 'place' answered" in err.value.message


payloads = st.one_of(
    st.binary(max_size=300),
    st.dictionaries(
        st.sampled_from(["task", "versions", "seeds", "extra"]),
        st.one_of(st.integers(), st.text(max_size=10), st.lists(st.integers(min_value=-3, max_value=3), max_size=3)),
    )
    .filter(lambda d: not (isinstance(d.get("task"), str) and d["task"] in VALID_TASKS))
    .map(lambda d: json.dumps(d).encode()),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(payload=payloads)
def test_garbage_evaluate_requests_get_one_error_reply(running: Running, payload: bytes) -> None:
    session = _session(running.endpoint)
    replies = list(session.get(KEYS.evaluate(WORKER_ID), payload=payload, timeout=20))
    assert len(replies) == 1
    (reply,) = replies
    assert reply.ok is None and reply.err is not None
    err = error_from_payload(reply.err.payload.to_bytes())
    assert err.code.value in ("invalid", "too_large", "not_found"), err


_SESSIONS: dict[str, zenoh.Session] = {}


def _session(endpoint: str) -> zenoh.Session:
    if endpoint not in _SESSIONS:
        _SESSIONS[endpoint] = zenoh.open(client_config(connect=[endpoint]))
    return _SESSIONS[endpoint]


@pytest.fixture(scope="module", autouse=True)
def _close_sessions() -> Iterator[None]:
    yield
    for s in _SESSIONS.values():
        s.close()
    _SESSIONS.clear()


def test_worker_survives_a_registry_restart_and_catches_up(tmp_path: Path) -> None:
    registry = start_pick_registry(tmp_path)
    endpoint = registry.endpoint
    worker = start_worker(
        endpoint, task="T1", log_path=tmp_path / "worker.log", extra=["--horizon", "20", "--worker-id", "w-restart"]
    )
    try:
        worker.read_until(is_episode, 60)
        registry.kill()  # SIGKILL: no goodbye
        worker.read_until(lambda x: x.get("event") == "registry" and x["connected"] is False, 30)
        away = worker.read_until(lambda x: is_episode(x) and not x["registry_connected"], 30)
        assert away["versions"] == {"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0}
        registry = start_server(tmp_path / "registry", port=registry.port)
        worker.read_until(lambda x: x.get("event") == "registry" and x["connected"] is True, 60)
        with Client([endpoint], actor="tester") as client:
            new = publish(client, "pick.lift", SLOW_LIFT)  # made after the restart
        swap = worker.read_until(lambda x: x.get("event") == "swap" and x.get("applied"), 30)
        assert (swap["name"], swap["to_version"]) == ("pick.lift", new.version)
        worker.read_until(lambda x: is_episode(x) and x["versions"]["pick.lift"] == new.version, 30)
    finally:
        code = worker.terminate()
        registry.stop()
    assert code == 0, worker.log()[-3000:]
    assert worker.read_until(lambda x: x.get("event") == "stopped", 1)["episodes"] >= 3
