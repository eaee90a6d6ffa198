"""The trace writer's C parts (``csrc/``, built as ``capevo.runtime.traces._native`` when the
package installs), or None in a source tree nobody built: each user falls back to the Python
version the C follows (queue.py, codec.py, mcapfile.py)."""

from __future__ import annotations

from types import ModuleType


def _load() -> ModuleType | None:
    try:
        from capevo.runtime.traces import _native
    except ImportError:
        return None
    return _native


NATIVE: ModuleType | None = _load()
