"""Spawned worker processes end without the interpreter's teardown once their work is sent.

Why: a worker that has imported torch, tensordict and torchrl takes about a second to finalise its interpreter
(module teardown and garbage collection; 2026-11-29: 1.1 s, 0.4 s with torch alone), and a process pool's shutdown
waits for it. `a3cqp evaluate --scene` spent ~1.2 s of its ~60 s there after the last result had arrived.

By the time the interpreter finalises, multiprocessing has run the worker's own exit work (its queues flushed, so
every result is sent; `multiprocessing.process.BaseProcess._bootstrap`), and Python has joined the worker's threads.
`install` registers an exit handler that flushes stdout and stderr and ends the process with `os._exit(0)`. Exit
handlers run last-registered first, so those that the libraries imported afterwards registered (torch, tqdm,
logging's flush) still run before it; only the teardown after them is skipped. For pool workers only: the exit
status is always 0 (a pool reads results and errors from its queues, not from exit codes).
"""

from __future__ import annotations

import atexit
import os
import sys

__all__ = ["install"]


def _exit_now() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):  # closed or replaced streams: nothing left to write
            pass
    os._exit(0)


def install() -> None:
    """In a worker process (e.g. a pool's initializer): end it without the interpreter's teardown at exit."""
    atexit.unregister(_exit_now)  # (once, however often a process calls it)
    atexit.register(_exit_now)
