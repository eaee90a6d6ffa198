"""A registry server that SIGKILLs itself between a commit and the read cache's update.

Run as ``python read_cache_crash_child.py <service arguments>``: it serves exactly as
``python -m capevo.registry.service`` does, except that a pointer move whose reason is
:data:`KILL_REASON` kills the process inside the read cache's listener, after SQLite has
made the move durable and before the cache has seen it.
"""

from __future__ import annotations

import os
import signal
import sys

from capevo.records import AuditEvent, EcmVersion
from capevo.registry import service
from capevo.registry.read_cache import ReadCache

KILL_REASON = "sigkill-before-the-cache-update"


def _update_or_die(self: ReadCache, event: AuditEvent, record: EcmVersion) -> None:
    if event.reason == KILL_REASON:
        os.kill(os.getpid(), signal.SIGKILL)
    ReadCache.current(self)


if __name__ == "__main__":
    ReadCache.on_event = _update_or_die  # type: ignore[method-assign]
    sys.exit(service.main(sys.argv[1:]))
