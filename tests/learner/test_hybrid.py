"""Hybrid learner: LLM structural edit (real local chat server) then CEM over the edited PARAMS."""

from __future__ import annotations

from learner_support import TARGET, ChatServer, SyntheticEvaluator

from capevo.learner.base import request_for
from capevo.learner.chat import Chat, ChatConfig
from capevo.learner.hybrid import HybridLearner
from capevo.learner.search import CemSearch
from capevo.learner.skills import seed_source
from capevo.learner.synthesis import LlmSynthesis
from capevo.records import Origin
from capevo.runtime.ecm.code import read_params


def _structural_edit() -> str:
    """v0 pick.reach with a new parameter (``descend_gain``) slowing the final descent."""
    source = seed_source("pick", "pick.reach")
    source = source.replace("    'dig': 0.0,\n}", "    'dig': 0.0,\n    'descend_gain': 0.5,\n}")
    old = '    return pose_action(np.array([err[0], err[1], err[2] - params["dig"]]), OPEN, params["gain"], rot)'
    assert old in source
    new = (
        '    move = np.array([err[0], err[1], (err[2] - params["dig"]) * params["descend_gain"]])\n'
        '    return pose_action(move, OPEN, params["gain"], rot)'
    )
    return source.replace(old, new)


def _learner(server: ChatServer | None, fake: SyntheticEvaluator, **kw) -> HybridLearner:
    chat = Chat(ChatConfig(base_url=server.base_url, model="m")) if server is not None else None
    cem = CemSearch(fake, population=6, iterations=3, episodes_per_candidate=2, seed=4, stop_when_passed=False)
    return HybridLearner(LlmSynthesis(chat, max_attempts=1), cem, **kw)


def test_llm_edit_then_cem_gives_a_hybrid_candidate(registry) -> None:
    request = request_for(registry, "pick", "pick.reach", train_seeds=list(range(10)))
    edited = _structural_edit()
    base = read_params(edited)
    assert "descend_gain" in base
    fake = SyntheticEvaluator("pick.reach", base, {**TARGET, "descend_gain": 1.0})
    with ChatServer([f"```python\n{edited}```"]) as server:
        cand = _learner(server, fake).learn(request)
    assert cand.spec.origin is Origin.HYBRID and cand.spec.parent == 0
    assert cand.spec.provenance.learner_id == "hybrid:llm:m+cem"
    # the edited code, with only PARAMS retuned
    head, tail = edited.split("PARAMS = {")[0], edited.split("\n}\n", 1)[1]
    assert cand.source.startswith(head) and cand.source.endswith(tail)
    assert set(read_params(cand.source)) == set(base)
    # every sample ran as hybrid code, starting from the LLM's own parameters
    assert fake.calls[0]["params"] == base
    assert {c["origin"] for c in fake.calls} == {Origin.HYBRID}
    assert len(fake.calls) == 18
    assert cand.score is not None and cand.baseline is not None and cand.score.key() >= cand.baseline.key()


def test_a_rejected_edit_falls_back_to_cem_on_the_parent(registry, tmp_path) -> None:
    request = request_for(registry, "pick", "pick.reach", train_seeds=list(range(10)))
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)
    marker = tmp_path / "MARKER"
    bad = f"```python\nimport os\nos.system('touch {marker}')\n\n\ndef act(obs, params):\n    return [0.0] * 7\n```"
    with ChatServer([bad]) as server:
        cand = _learner(server, fake).learn(request)
    assert not marker.exists()
    assert cand.spec.origin is Origin.CLONE
    assert "LLM edit rejected" in cand.notes["fallback"]
    assert fake.calls[0]["params"] == base
    assert {c["origin"] for c in fake.calls} == {Origin.CLONE}


def test_without_an_endpoint_hybrid_is_plain_cem(registry) -> None:
    request = request_for(registry, "pick", "pick.reach", train_seeds=list(range(10)))
    fake = SyntheticEvaluator("pick.reach", read_params(request.source), TARGET)
    cand = _learner(None, fake).learn(request)
    assert cand.spec.origin is Origin.CLONE
    assert cand.notes["fallback"] == "no chat endpoint configured"
