"""What a neural learner carries from one iteration to the next, on disk (issue 19: learning
accumulates across iterations).

Without it, every iteration's SAC or BC update starts again from the *active* version: when the
gate rejects a candidate, the next iteration throws the candidate's training away and starts
from the same point, so updates never add up. A :class:`LearnerState` directory keeps, per ECM:

* ``latest.zip``: the learner's latest candidate (SAC zip with actor, critics, optimizers), which
  the next update of the ECM continues from whether or not the gate promoted it;
* ``replay.pkl``: SAC's replay buffer (SB3's own ``save_replay_buffer`` format), so off-policy
  experience is kept too;
* ``demos.npz``: every demonstration row behaviour cloning has used so far (scripted rollouts and
  the successful traces of every iteration), so imitation keeps the data of earlier iterations.

The candidate the gate judges is still the learner's output; only the learner's starting point
changes. The directory belongs to one run (the evolve report directory holds it), so a resumed run
continues too. Files are written to a temporary name and renamed, so a crash leaves the previous
state or the new one, never a torn file.

Invariants:
1. After :meth:`LearnerState.save_latest`, :meth:`LearnerState.latest` returns the same bytes,
   also from a new :class:`LearnerState` on the same directory.
2. :meth:`LearnerState.add_demos` returns the union of the stored rows and the new ones (stored
   first); a later :meth:`LearnerState.demos` returns exactly those rows.
3. No file is ever left half-written under its final name.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.records.names import validate_name

LATEST = "latest.zip"
REPLAY = "replay.pkl"
DEMOS = "demos.npz"


@contextmanager
def _replacing(path: Path) -> Iterator[Path]:
    """A temporary path in ``path``'s directory that is renamed onto ``path`` if the block succeeds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


class LearnerState:
    """One ECM's learner state under ``root/<ecm>/``.

    Args:
        root: The run's learner-state directory (created on first write).
        ecm: The ECM this state belongs to.

    Raises:
        Invalid: a bad ECM name.
    """

    def __init__(self, root: str | os.PathLike[str], ecm: str) -> None:
        validate_name(ecm)
        self.ecm = ecm
        self.directory = Path(root) / ecm

    # --- the latest candidate ------------------------------------------------------------

    def latest(self) -> bytes | None:
        """The latest candidate's artifact, or None before the first update."""
        path = self.directory / LATEST
        return path.read_bytes() if path.is_file() else None

    def save_latest(self, artifact: bytes) -> None:
        with _replacing(self.directory / LATEST) as tmp:
            tmp.write_bytes(artifact)

    # --- SAC's replay buffer ---------------------------------------------------------------

    def load_replay(self, model: Any) -> int:
        """Load the stored replay buffer into ``model`` (an SB3 off-policy model); returns its size.

        The file is SB3's pickle, written by :meth:`save_replay` of this run (never an artifact
        from the registry, which capevo loads without unpickling).
        """
        path = self.directory / REPLAY
        if not path.is_file():
            return 0
        model.load_replay_buffer(str(path))
        buffer = model.replay_buffer
        return int(buffer.buffer_size if buffer.full else buffer.pos)

    def save_replay(self, model: Any) -> None:
        with _replacing(self.directory / REPLAY) as tmp:
            model.save_replay_buffer(str(tmp))

    # --- demonstrations ------------------------------------------------------------------

    def demos(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The stored demonstration rows ``(obs, action)``, or None when there are none."""
        path = self.directory / DEMOS
        if not path.is_file():
            return None
        with np.load(path) as data:
            return data["obs"].astype(np.float32), data["action"].astype(np.float32)

    def add_demos(self, obs: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Store the stored rows followed by ``obs``/``action``; returns all of them.

        Raises:
            Invalid: rows whose widths differ from the stored ones (another interface).
        """
        stored = self.demos()
        if stored is not None and len(stored[0]):
            if stored[0].shape[1] != obs.shape[1] or stored[1].shape[1] != action.shape[1]:
                raise Invalid(
                    f"{self.ecm}: stored demonstrations are {stored[0].shape[1]}->{stored[1].shape[1]} wide, "
                    f"new ones {obs.shape[1]}->{action.shape[1]}",
                    details={"field": "demos"},
                )
            obs = np.concatenate([stored[0], obs])
            action = np.concatenate([stored[1], action])
        with _replacing(self.directory / DEMOS) as tmp, open(tmp, "wb") as f:
            np.savez(f, obs=obs.astype(np.float32), action=action.astype(np.float32))
        return obs.astype(np.float32), action.astype(np.float32)
