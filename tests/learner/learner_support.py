"""Shared pieces of the learner tests: a synthetic candidate evaluator and a real chat server.

:class:`SyntheticEvaluator` is a fake (pure python, no simulator) of the narrow
:class:`~capevo.learner.base.CandidateEvaluator` protocol, for optimizer unit tests.
:class:`ChatServer` is a real HTTP server on 127.0.0.1 speaking the OpenAI
``/v1/chat/completions`` JSON shape, replying from a script.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Mapping, Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from capevo.records import Origin
from capevo.runtime.ecm.code import read_params
from capevo.runtime.evaluation import EpisodeOutcome

TARGET = {"gain": 9.0, "hover": 0.08, "grasp_dz": 0.0, "descend_xy": 0.02, "dig": 0.01}


class SyntheticEvaluator:
    """A pure-python CandidateEvaluator (a fake: no simulator).

    An episode succeeds when the overridden ECM's PARAMS are within a seed-dependent radius of
    ``target`` (normalized distance); reward per step is 1 - distance. Records every call.
    """

    def __init__(self, ecm: str, base: Mapping[str, float], target: Mapping[str, float]) -> None:
        self.ecm = ecm
        self.base = dict(base)
        self.target = dict(target)
        self.calls: list[dict] = []

    def distance(self, params: Mapping[str, float]) -> float:
        return math.sqrt(
            sum(((params[k] - v) / max(abs(self.base[k]), 0.01)) ** 2 for k, v in self.target.items())
            / len(self.target)
        )

    def evaluate(
        self,
        task: str,
        versions: Mapping[str, int],
        seeds: Sequence[int],
        *,
        overrides: Mapping[str, bytes] | None = None,
        override_origin: Origin | None = None,
    ) -> list[EpisodeOutcome]:
        params = read_params(overrides[self.ecm].decode()) if overrides else self.base
        self.calls.append({"params": params, "seeds": tuple(seeds), "origin": override_origin})
        d = self.distance(params)
        out = []
        for s in seeds:
            radius = 0.25 + 0.1 * ((s * 7919) % 10) / 10
            steps = 50
            out.append(outcome(s, versions, success=d < radius, reward=(1.0 - d) * steps, steps=steps))
        return out


def outcome(
    seed: int, versions: Mapping[str, int], *, success: bool = False, reward: float = 0.0, steps: int = 1
) -> EpisodeOutcome:
    """One evaluated episode of a fake evaluator: no interventions, unsafe steps or failures."""
    return EpisodeOutcome(
        seed=seed,
        success=success,
        reward=reward,
        steps=steps,
        duration_s=0.0,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set=dict(versions),
    )


class ChatServer:
    """A real OpenAI-compatible chat endpoint on loopback, answering from ``replies`` in order.

    Each reply is a string (sent as the assistant message) or an int (sent as that HTTP
    status with an error body). Every request body is kept in :attr:`requests`.
    """

    def __init__(self, replies: Sequence[str | int]) -> None:
        self.replies = list(replies)
        self.requests: list[dict[str, Any]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:
                pass

            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length", "0"))
                body = json.loads(self.rfile.read(length))
                server.requests.append({"path": self.path, "body": body, "auth": self.headers.get("Authorization")})
                reply = server.replies.pop(0) if server.replies else 503
                if self.path != "/v1/chat/completions":
                    reply = 404
                if isinstance(reply, int):
                    data = json.dumps({"error": {"message": "nope"}}).encode()
                    self.send_response(reply)
                else:
                    data = json.dumps(
                        {
                            "id": "chatcmpl-test",
                            "object": "chat.completion",
                            "model": body.get("model"),
                            "choices": [
                                {
                                    "index": 0,
                                    "message": {"role": "assistant", "content": reply},
                                    "finish_reason": "stop",
                                }
                            ],
                        }
                    ).encode()
                    self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"

    def __enter__(self) -> ChatServer:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)
