"""Stopping long jobs cleanly: SIGTERM handled as Ctrl-C (one home).

``kill PID`` is how a session's long jobs (the labeling campaign, trainings) are stopped, and a
job started in the background by a non-interactive shell (``nohup ... &``) ignores SIGINT, so
Ctrl-C's ``kill -INT`` cannot reach it. Within :func:`terminate_as_interrupt` SIGTERM raises
``KeyboardInterrupt`` as Ctrl-C does: the job stops through its ``finally`` clauses (the campaign
writes its finished labels as a last shard, the trainer snapshots its last finished epoch).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises ``KeyboardInterrupt``; the previous handler is restored
    on exit. Outside the main thread (where Python cannot set handlers) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
