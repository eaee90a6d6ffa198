"""Hybrid learner: an LLM edits the code's structure, then CEM fine-tunes its numeric PARAMS.

:class:`HybridLearner` asks :class:`~capevo.learner.synthesis.LlmSynthesis` for a validated,
smoke-tested source, then runs :class:`~capevo.learner.search.CemSearch` over *that* source's
``PARAMS`` (which the model may have changed), evaluating every sample as origin ``hybrid``
(so under the trust given to LLM-written code, i.e. sandboxed by default). The candidate is
the edited code with the best parameters, origin ``hybrid``.

Without an endpoint, or when every model reply is rejected or the endpoint fails, it logs a
warning and returns plain CEM on the parent's source (origin of the search, ``clone`` by
default), with ``notes["fallback"]`` saying why.

Invariants:
1. Code from the model runs only after it passed validation: its smoke run in a sandbox
   worker, its search episodes as origin ``hybrid`` (sandboxed under the default trust).
2. A ``hybrid`` candidate's source is the accepted LLM source with only ``PARAMS`` changed.
"""

from __future__ import annotations

import logging

from capevo.errors import Invalid, SandboxViolation, Timeout, Unavailable
from capevo.learner.base import Candidate, LearnRequest, config_hash
from capevo.learner.experience import trace_paths
from capevo.learner.search import CemSearch, candidate_spec
from capevo.learner.synthesis import LlmSynthesis
from capevo.records import Origin, Provenance

log = logging.getLogger(__name__)


class HybridLearner:
    """LLM structural edit followed by CEM over the edited code's parameters.

    Args:
        synthesis: Proposes the edited source.
        search: Tunes its parameters (its evaluator runs the samples).
        origin: Origin of hybrid candidates.
    """

    def __init__(self, synthesis: LlmSynthesis, search: CemSearch, *, origin: Origin = Origin.HYBRID) -> None:
        self.synthesis = synthesis
        self.search = search
        self.origin = Origin(origin)
        self.learner_id = f"hybrid:{synthesis.learner_id}+{search.learner_id}"

    def _fallback(self, request: LearnRequest, why: str) -> Candidate:
        log.warning("hybrid learner for %s: %s; falling back to %s", request.ecm, why, self.search.learner_id)
        return self.search.learn(request).with_notes(fallback=why)

    def learn(self, request: LearnRequest) -> Candidate:
        """Edit with the LLM, tune with CEM; fall back to CEM alone (see the module docstring).

        Raises:
            CapevoError: whatever the CEM search raised.
        """
        if self.synthesis.chat is None:
            return self._fallback(request, "no chat endpoint configured")
        try:
            source, attempts = self.synthesis.propose_source(request)
        except (SandboxViolation, Invalid, Timeout, Unavailable) as exc:
            return self._fallback(request, f"LLM edit rejected or unavailable: {exc}")
        result = self.search.search(request, source=source, evaluation_origin=self.origin)
        config = {
            "method": "hybrid",
            "llm": self.synthesis.config(),
            "cem": self.search.config.to_dict(),
            "task": request.task,
            "ecm": request.ecm,
            "parent": request.parent.version,
            "train_seeds": list(request.train_seeds),
        }
        provenance = Provenance(
            learner_id=self.learner_id, config_hash=config_hash(config), traces=trace_paths(request.outcomes)
        )
        return Candidate(
            ecm=request.ecm,
            artifact=result.source.encode(),
            spec=candidate_spec(request, origin=self.origin, provenance=provenance),
            score=result.score,
            baseline=result.baseline,
            notes={
                "learner": self.learner_id,
                "attempts": [a.to_dict() for a in attempts],
                "params": dict(result.params),
                "iterations_run": result.iterations_run,
                "episodes_run": result.episodes_run,
            },
            experience=result.experience,
        )
