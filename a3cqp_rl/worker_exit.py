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
"""

from __future__ import annotations

import atexit
import importlib
import os
import sys

__all__ = ["install", "initializer"]


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


def initializer(target: str, *args: object) -> None:
    """A process pool's initializer: `install`, then `target(*args)` ("module:function"), whose module is imported
    only now, so that the exit handlers of what it imports (torch, ...) run before the worker ends."""
    install()
    module, name = target.split(":")
    getattr(importlib.import_module(module), name)(*args)
