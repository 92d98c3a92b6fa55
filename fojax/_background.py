"""Ground floor (any package may import it; docs/CONTRIBUTING.md). One helper: run a
function on a worker thread (used to compile XLA programs while the
main thread works; XLA compiles without holding the GIL).

The worker is a `concurrent.futures` thread, *not* a daemon: when a run ends early (Ctrl-C,
SIGTERM turned into an exception by `fojax.cli`), the interpreter waits for a compilation in
progress to finish (seconds) before it exits, instead of tearing XLA down under a running
compiler thread. Errors are re-raised by ``future.result()``; callers that only wait
(``concurrent.futures.wait``) leave them to the later call that needs the program, which
raises the same error itself.
"""

from __future__ import annotations

import concurrent.futures


def in_background(fn, *args) -> concurrent.futures.Future:
    """``fn(*args)`` on a new worker thread; a future of its result."""
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="fojax-compile")
    try:
        return pool.submit(fn, *args)
    finally:
        pool.shutdown(wait=False)  # the thread ends with fn; nothing else is queued
