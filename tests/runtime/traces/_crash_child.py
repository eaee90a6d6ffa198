"""Child process for the SIGKILL tests: writes env steps until the parent kills it.

Usage: python _crash_child.py PATH MODE FLUSH_INTERVAL_S N

Modes (each reports on stdout, one line per report, and never exits by itself):
- ``explicit``: write N steps, call ``flush()``, print N, keep writing.
- ``idle``: write N steps, print N, sleep (only the background thread can flush).
- ``continuous``: write a step every millisecond; every 20 steps print ``count monotonic``.
"""

from __future__ import annotations

import sys
import time

from capevo.records import CapabilitySet
from capevo.runtime.traces import EnvStep, TraceMetadata, TraceWriter


def main() -> None:
    path, mode, interval, n = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
    meta = TraceMetadata(
        run_id="crash",
        task="Lift",
        capability_set=CapabilitySet(revision=1, active={"reach": 1}),
        phi_hash="p",
        agent_identity_hash="a",
        seeds=(0,),
    )
    # A huge chunk_size: only the time-based or explicit flush may put data on disk.
    w = TraceWriter(path, meta, chunk_size=1 << 30, flush_interval_s=interval)

    def step(i: int) -> None:
        w.write_env_step(
            EnvStep(
                episode=0,
                step=i,
                ecm="reach",
                version=1,
                obs=(float(i),) * 50,
                action=(0.5,) * 7,
                reward=1.0,
                next_obs=(float(i + 1),) * 50,
            )
        )

    i = 0
    if mode in ("explicit", "idle"):
        for i in range(n):
            step(i)
        if mode == "explicit":
            w.flush()
        print(n, flush=True)
        i = n
        while True:
            if mode == "explicit":
                step(i)
                i += 1
                time.sleep(0.001)
            else:
                time.sleep(60)
    while True:  # continuous
        step(i)
        i += 1
        if i % 20 == 0:
            print(i, time.monotonic(), flush=True)
        time.sleep(0.001)


if __name__ == "__main__":
    main()
