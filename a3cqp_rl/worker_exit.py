"""Spawned worker processes end without the interpreter's teardown once their work is sent.

Why: a worker that has imported torch, tensordict and torchrl takes about a second to finalise its interpreter
(module teardown and garbage collection; 2026-11-29: 1.1 s, 0.4 s with torch alone), and a process pool's shutdown
waits for it. `a3cqp evaluate --scene` spent ~1.2 s of its ~60 s there after the last result had arrived.

By the time the interpreter finalises, multiprocessing has run the worker's own exit work (its queues flushed, so
every result is sent; `multiprocessing.process.BaseProcess._bootstrap`), and Python has joined the worker's threads.
`install` registers an exit handler that shuts logging down, flushes stdout and stderr and ends the process with
`os._exit(0)`. Exit handlers run last-registered first: those registered after it (by what the worker imports
later) run before it, those registered before it are skipped. A pool's `initializer` installs it before the
pool's own set-up imports anything (torch registers six handlers on import). For pool workers only: the exit
status is always 0 (a pool reads results and errors from its queues, not from exit codes).

A worker also ends, with status 1, as soon as the process that owns its pool ends (`watch_owner`): killed (SIGTERM,
SIGKILL, a `timeout`), the owner leaves its workers waiting on queues whose other end each worker holds itself, so
they would wait forever, a busy one simulating on to the end of its job first (2026-12-02: `a3cqp evaluate` killed
after 10 s left its two workers and the fork server behind, the workers asleep on a pipe for good).
"""

from __future__ import annotations

import atexit
import importlib
import os
import select
import sys
import threading
import time

__all__ = ["install", "initializer", "watch_owner"]

OWNER_POLL_SECONDS = 1.0
"""Where a process cannot be waited on through a pidfd (not Linux, or a kernel before 5.3): how often a worker looks
whether its pool's owner is still there [s]."""


def _exit_now() -> None:
    if "logging" in sys.modules:  # its own exit handler was registered first (concurrent.futures imports it)
        sys.modules["logging"].shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):  # closed or replaced streams: nothing left to write
            pass
    os._exit(0)


def install() -> None:
    """In a worker process: end it without the interpreter's teardown, after the exit handlers registered later."""
    atexit.unregister(_exit_now)  # (once, however often a process calls it)
    atexit.register(_exit_now)


def _owner_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # there, but not ours to signal
        return False
    try:  # an owner that ended but was not yet reaped by its own parent is a zombie: gone too
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (OSError, IndexError):
        return False


def _wait_for(pid: int) -> None:
    try:
        fd = os.pidfd_open(pid)  # readable once the process has ended, reaped or not
    except ProcessLookupError:
        os._exit(1)
    except (AttributeError, OSError):  # no pidfd here: poll
        while not _owner_gone(pid):
            time.sleep(OWNER_POLL_SECONDS)
        os._exit(1)
    select.select([fd], [], [])
    os._exit(1)


def watch_owner(pid: int) -> None:
    """In a worker process: end it at once (status 1, nothing left to send) when the process `pid` ends."""
    threading.Thread(target=_wait_for, args=(pid,), name="watch-owner", daemon=True).start()


def initializer(owner: int, target: str, *args: object) -> None:
    """A process pool's initializer: `install`, `watch_owner(owner)` (the pid of the process that made the pool),
    then `target(*args)` ("module:function"), whose module is imported only now, so that the exit handlers of what it
    imports (torch, ...) run before the worker ends."""
    install()
    watch_owner(owner)
    module, name = target.split(":")
    getattr(importlib.import_module(module), name)(*args)
