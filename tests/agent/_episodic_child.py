"""Child process for the M_ep SIGKILL test: appends episodes until the parent kills it.

Usage: python _episodic_child.py PATH

After each ``append`` returns it prints the record's seed; it never exits by itself.
"""

from __future__ import annotations

import sys

from capevo.agent import EpisodeRecord, EpisodicMemory


def main() -> None:
    memory = EpisodicMemory(sys.argv[1])
    i = 0
    while True:
        memory.append(
            EpisodeRecord(
                iteration=i // 10,
                task="pick",
                seed=i,
                success=i % 3 == 0,
                reward=i * 0.5,
                steps=100 + i,
                capability_set={"pick.reach": 1, "pick.grasp": 2, "pick.lift": 1 + i // 10},
                trace=f"runs/{i}.mcap",
            )
        )
        print(i, flush=True)
        i += 1


if __name__ == "__main__":
    main()
