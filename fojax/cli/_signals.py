"""How the ``fojax`` command ends on SIGINT (Ctrl-C) and SIGTERM.

`Interrupts` is installed by `fojax.cli.main` around every command. A signal is
*recorded* (`Interrupts.signum`) and interrupts the command once, by raising
`KeyboardInterrupt` in the main thread (so that the atomic writers remove their
temporary files on the way out). What can go wrong with a plain
``KeyboardInterrupt`` handler, and what is done about it:

- **The exception lands in a finalizer** (a ``__del__`` or a weakref callback, e.g.
  of JAX's caches, run by the garbage collector in the middle of the Monte Carlo run):
  Python prints ``Exception ignored in ...`` with a traceback and carries on, so the
  interruption is lost and the study ends with exit code 0. Here the
  ``sys.unraisablehook`` recognises the swallowed interruption, prints nothing and
  raises it again a moment later, outside the finalizer; `check` (called by the
  commands between their phases, e.g. after every tuning step) and the end of `main`
  honour the recorded signal as well, so a command that got a signal never exits 0.
- **The exception leaves a JAX compilation running.** jaxlib 0.10.2 compiles on a
  thread of its own thread pool (``PjRtCompiler::CompileAndLoad``) and the main thread
  waits for it interruptibly; a ``KeyboardInterrupt`` ends the wait, not the
  compilation. When the interpreter then shuts down normally it destroys the PjRt
  client and its devices while that thread is still compiling, and the thread
  crashes in ``xla::ifrt::SingleDeviceSharding::Create`` (SIGSEGV, exit code 139;
  seen with gdb). So the command, once its files are complete and its message is
  printed, leaves with ``os._exit`` (no interpreter shutdown, no destructors: every
  file was already written, flushed and fsync'ed by the atomic writers).
- **A signal while Python imports fojax** (before `main` runs; the import of JAX, SciPy,
  cvxpy and matplotlib takes seconds): `quiet_while_starting`, called first thing by the
  program's entry point (``_fojax_program.py``, before fojax is imported), ends the process
  with one line and exit code 130/143 (nothing is written before `main`).
- **A signal that is ignored** when the program starts (``SIG_IGN``, e.g. a background
  job of a non-interactive shell) stays ignored.
- **A signal while a tuning checkpoint pair is written** (``.npz`` + ``.json``, which
  must agree) is deferred until the pair is complete.
"""

from __future__ import annotations

import signal
import sys
import threading
import time


#: the `Interrupts` of the running command (None outside `fojax.cli.main`)
_current: Interrupts | None = None


class Interrupts:
    """Context manager: SIGINT/SIGTERM are recorded and raise `KeyboardInterrupt` once in
    the main thread, except while a tuning checkpoint (an ``.npz`` + ``.json`` pair) is
    being written: then the interruption happens right after that write. An
    interruption swallowed by a finalizer is raised again (see the module docstring).
    Outside the main thread it installs nothing."""

    #: (function name, part of its file path) of writers that must not be interrupted
    PAIRED_WRITERS = (("save_checkpoint", "tuning"),)

    def __init__(self):
        self.signum = None
        self.message = None  # what `main` prints after "fojax: interrupted; " (see on_interrupt)
        self._old = {}
        self._old_hook = None
        self._waiting = False
        self._raised = False  # a KeyboardInterrupt for the recorded signal is on its way
        self._reraising = False  # a helper thread will raise it again (`_schedule_reraise`)
        self._finishing = False

    # ------------------------------------------------------------------ installing
    def __enter__(self):
        global _current

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                if signal.getsignal(sig) is not signal.SIG_IGN:  # an inherited "ignore" stays
                    self._old[sig] = signal.signal(sig, self._handler)
            self._old_hook = sys.unraisablehook
            sys.unraisablehook = self._unraisable
            self._previous, _current = _current, self
        return self

    def __exit__(self, *exc):
        global _current

        for sig, old in self._old.items():
            signal.signal(sig, old)
        if self._old_hook is not None:
            sys.unraisablehook = self._old_hook
            _current = self._previous
        self._old.clear()
        self._old_hook = None
        return False

    # ------------------------------------------------------------------ state
    @property
    def exit_code(self) -> int | None:
        """``128 + signal number`` (130 for SIGINT, 143 for SIGTERM), or None."""
        return None if self.signum is None else 128 + int(self.signum)

    def check(self) -> None:
        """Raise `KeyboardInterrupt` if a signal was received (a safe point of a command)."""
        if self.signum is not None and not self._finishing:
            self._raised = True
            raise KeyboardInterrupt

    def finish(self) -> None:
        """The interruption has arrived where it is handled: further signals are only
        recorded (a second Ctrl-C does not cut the final message or clean-up short)."""
        self._finishing = True

    # ------------------------------------------------------------------ handlers
    @classmethod
    def _in_paired_write(cls, frame) -> bool:
        return _on_stack(frame, lambda code: any(code.co_name == n and part in code.co_filename
                                                 for n, part in cls.PAIRED_WRITERS))

    def _handler(self, signum, frame):
        self.signum = self.signum or signum
        if self._finishing or self._raised:
            return  # recorded; the interruption is already on its way
        if _on_stack(frame, _is_hook):
            # inside our own unraisable hook: an exception raised here would be swallowed too
            # ("Exception ignored in sys.unraisablehook"); the helper thread raises it once
            # the hook has returned
            self._schedule_reraise()
            return
        if self._in_paired_write(frame):
            if not self._waiting:  # interrupt once the write is complete
                self._waiting = True
                threading.Thread(target=self._after_write, args=(threading.main_thread().ident,),
                                 daemon=True).start()
            return
        self._raised = True
        raise KeyboardInterrupt

    def _after_write(self, main_id):
        while self._in_paired_write(sys._current_frames().get(main_id)):
            time.sleep(0.01)
        self._waiting = False
        self._interrupt_main(main_id)

    def _unraisable(self, unraisable):
        """``sys.unraisablehook``: our KeyboardInterrupt was raised inside a finalizer and
        ignored by Python. Print nothing and raise it again from a helper thread (a
        signal simulated with `_thread.interrupt_main` once this hook has returned)."""
        if (
            self.signum is None
            or unraisable.exc_type is None
            or not issubclass(unraisable.exc_type, KeyboardInterrupt)
        ):
            return self._old_hook(unraisable)
        if self._finishing:
            return None
        self._raised = False
        self._schedule_reraise()
        return None

    def _schedule_reraise(self):
        """Start the helper thread that raises the interruption again (once)."""
        if self._reraising:
            return
        self._reraising = True
        threading.Thread(target=self._reraise, args=(threading.main_thread().ident,), daemon=True).start()

    def _reraise(self, main_id):
        """Interrupt the main thread once it has left `_unraisable` (a signal simulated with
        `_thread.interrupt_main`). Waiting for that, not for a fixed moment: on a loaded
        machine the main thread can still be inside the hook after any fixed delay, and a
        KeyboardInterrupt raised there is swallowed ("Exception ignored in
        sys.unraisablehook") and the command runs on."""
        while _on_stack(sys._current_frames().get(main_id), _is_hook):
            time.sleep(0.001)
        self._reraising = False
        self._interrupt_main(main_id)

    def _interrupt_main(self, main_id):
        """Deliver the recorded signal to the main thread again, now that it may raise there.

        A real signal (``pthread_kill``), not `_thread.interrupt_main`: a simulated signal is
        only seen when the main thread next runs Python code, so a main thread blocked in a
        system call (a ``time.sleep``, a read) stays blocked until the call returns (a SIGINT
        that arrives while a tuning checkpoint is written would wait for whatever blocking call
        follows the write). Only
        while this command's handler is installed (after `__exit__` the signal's own
        disposition would apply: SIGTERM would end the process unannounced); elsewhere, and on
        platforms without ``pthread_kill``, the simulated signal."""
        import _thread

        if hasattr(signal, "pthread_kill") and signal.getsignal(self.signum) == self._handler:
            signal.pthread_kill(main_id, self.signum)
        else:
            _thread.interrupt_main(self.signum)


def _is_hook(code) -> bool:
    """Whether `code` is `Interrupts._unraisable`'s (the unraisable hook)."""
    return code is Interrupts._unraisable.__code__


def _on_stack(frame, match) -> bool:
    """Whether the code object of `frame` or of one of its callers satisfies `match`."""
    while frame is not None:
        if match(frame.f_code):
            return True
        frame = frame.f_back
    return False


def check() -> None:
    """Raise `KeyboardInterrupt` if the running ``fojax`` command received SIGINT/SIGTERM
    (no-op outside a command). Commands call it between their phases."""
    if _current is not None:
        _current.check()


def on_interrupt(message: str) -> None:
    """The line (after ``fojax: interrupted; ``) printed if the running command is
    interrupted from now on, e.g. how to resume a study."""
    if _current is not None:
        _current.message = message


def _starting(signum, frame):
    import os

    os.write(2, b"fojax: interrupted while starting; no file was written\n")
    os._exit(128 + signum)


def quiet_while_starting() -> None:
    """Until `fojax.cli.main` takes over, SIGINT and SIGTERM end the ``fojax`` program at
    once with one line on stderr and exit code 130/143 (instead of a traceback from deep
    inside an import). Called by the program's entry point (``_fojax_program.py``) only,
    before fojax is imported."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _starting)
