"""A registry round trip over real Zenoh: the smallest end-to-end demonstration.

It serves a registry root in a background thread (a router-mode Zenoh session on a
loopback port), connects a :class:`Client` to it, publishes two versions of a code ECM,
promotes both, rolls back, and returns the audit history the registry recorded.

Invariants:
1. Every mutation goes through the Zenoh client, never the in-process registry.
2. After the round trip the active version is the first one again, and the history holds
   exactly publish, promote, publish, promote, rollback for the demo ECM, in that order.
"""

from __future__ import annotations

import socket
import threading
from dataclasses import dataclass
from pathlib import Path

from capevo.errors import Unavailable
from capevo.records import AuditEvent, Descriptor, Interface, IOSpec, Kind, PublishSpec
from capevo.registry.client import Client
from capevo.registry.service import serve

DEMO_ECM = "demo.reach"
_SOURCE = '''"""Move the open gripper towards a hover point above the object."""
import numpy as np

PARAMS = {{"gain": {gain}, "hover": 0.10}}


def act(obs, params):
    target = obs["object_pos"] + np.array([0.0, 0.0, params["hover"]])
    move = np.clip((target - obs["robot0_eef_pos"]) * params["gain"], -1.0, 1.0)
    return [move[0], move[1], move[2], 0.0, 0.0, 0.0, -1.0]
'''
_SPEC = PublishSpec(
    kind=Kind.CODE,
    descriptor=Descriptor(description="Move the open gripper to a hover point above the object."),
    interface=Interface(
        inputs=(IOSpec(name="robot0_eef_pos", shape=(3,), units="m"), IOSpec(name="object_pos", shape=(3,), units="m")),
        outputs=(IOSpec(name="action", shape=(7,), low=-1.0, high=1.0),),
    ),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class RoundTrip:
    """What the round trip did and what the registry recorded."""

    endpoint: str
    active_version: int
    history: tuple[AuditEvent, ...]


def _free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_round_trip(root: str | Path, *, port: int | None = None, startup_timeout_s: float = 30.0) -> RoundTrip:
    """Serve ``root`` over Zenoh on loopback and drive a publish/promote/rollback cycle through a client.

    Raises:
        Unavailable: the registry did not come up within ``startup_timeout_s``.
        CapevoError: any registry error the client reports.
    """
    endpoint = f"tcp/127.0.0.1:{port or _free_loopback_port()}"
    ready = threading.Event()
    stop = threading.Event()
    failure: list[BaseException] = []

    def _serve() -> None:
        try:
            serve(root, listen=[endpoint], ready=ready, stop=stop, multicast_scouting=False, handle_signals=False)
        except BaseException as exc:  # reported to the caller below, not swallowed
            failure.append(exc)
            ready.set()

    server = threading.Thread(target=_serve, name="capevo-registry", daemon=True)
    server.start()
    try:
        if not ready.wait(startup_timeout_s) or failure:
            raise Unavailable(f"registry did not start on {endpoint}: {failure[0] if failure else 'timed out'}")
        with Client([endpoint], actor="demo") as client:
            v0 = client.publish(DEMO_ECM, _SOURCE.format(gain=4.0).encode(), _SPEC)
            client.promote(DEMO_ECM, v0.version, reason="first version")
            v1 = client.publish(DEMO_ECM, _SOURCE.format(gain=8.0).encode(), _SPEC)
            client.promote(DEMO_ECM, v1.version, expected_active=v0.version, reason="higher gain")
            client.rollback(DEMO_ECM, expected_active=v1.version, reason="demo: undo the gain change")
            active = client.get_version(DEMO_ECM).version
            history = tuple(client.history(DEMO_ECM))
    finally:
        stop.set()
        server.join(timeout=30)
    return RoundTrip(endpoint=endpoint, active_version=active, history=history)


__all__ = ["DEMO_ECM", "RoundTrip", "run_round_trip"]
