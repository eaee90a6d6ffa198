"""The trace files that a list of paths names: files as given, directories for their ``*.mcap``.

``capevo trace blame``, behaviour cloning's trace loader and the learner worker's episode feed
all take "trace files, or directories of them". They differ only in two choices, which are
arguments here: whether a directory's subdirectories count (a report's ``traces/`` has one per
evaluation), and whether a missing path or an empty directory is an error (for a command a
user typed) or simply nothing yet (for a learner polling a directory a runtime still fills).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from capevo.errors import NotFound

TRACE_GLOB = "*.mcap"


def trace_files(
    paths: Iterable[str | os.PathLike[str]], *, recursive: bool = False, missing_ok: bool = False
) -> list[Path]:
    """The trace files ``paths`` name, each once (resolved), in the order given.

    A file is taken as given, whatever its suffix; a directory gives its ``*.mcap`` files in
    name order (with ``recursive``, those of every subdirectory too).

    Raises:
        NotFound: unless ``missing_ok``, a path that does not exist, or a directory holding no
            trace file.
    """
    found: list[Path] = []
    for given in paths:
        path = Path(given)
        if path.is_dir():
            in_dir = sorted(path.rglob(TRACE_GLOB) if recursive else path.glob(TRACE_GLOB))
            if not in_dir and not missing_ok:
                raise NotFound(f"no {TRACE_GLOB} file under {path}", details={"path": str(path)})
            found.extend(in_dir)
        elif path.exists():
            found.append(path)
        elif not missing_ok:
            raise NotFound(f"no such trace: {path}", details={"path": str(path)})
    return list(dict.fromkeys(f.resolve() for f in found))
