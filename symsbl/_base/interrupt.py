"""Ctrl-C that survives the libraries it passes through.

Python turns SIGINT into ``KeyboardInterrupt`` at the next bytecode, which may be inside Python code
that a C library calls: CasADi's SUNDIALS callbacks consume it and report a solver failure, its SWIG
layer drops one raised while it inspects an argument (and tries the next overload), and one raised
inside a ``DM`` conversion comes back as another exception. While :func:`sigint_recorded` is active
each SIGINT is also counted, so a caller can tell that Ctrl-C was pressed whatever became of the
exception; a block that asks for it gets the interrupt raised again while it is still running.

Before all that, while the ``symsbl`` command is still importing (a second or two: numpy, scipy, sympy,
CasADi), an interrupt would end in a traceback of the import machinery, or in an ImportError that a C
extension made of it. When this process is the command (the ``symsbl`` script or ``python -m symsbl``),
importing this module, the package's first import, installs a handler that prints the one line and
exits with 130 at once (nothing has been written yet); the command hands SIGINT back to Python
(:func:`command_started`) before its own handling begins. A program that imports symsbl is not affected.
"""

from __future__ import annotations

import _thread
import contextlib
import ctypes
import os
import signal
import sys
import threading

__all__ = ["sigint_recorded", "interrupt_handled", "command_started"]

_PRESSES = 0
_REPEATS: dict[object, float] = {}  # the repeat intervals of the open blocks that asked for one
_TIMERS: list[threading.Timer] = []
_LOCK = threading.RLock()  # re-entrant: the handler runs in the main thread, possibly while it holds the lock


def _again():
    with _LOCK:
        if _REPEATS:
            _thread.interrupt_main(signal.SIGINT)  # runs the installed handler at the main thread's next bytecode


def _record(signum, frame):
    global _PRESSES
    _PRESSES += 1
    with _LOCK:
        if _REPEATS:
            timer = threading.Timer(min(_REPEATS.values()), _again)
            timer.daemon = True
            _TIMERS.append(timer)
            timer.start()
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigint_recorded(repeat: float | None = None):
    """Count SIGINT inside the block (it still raises ``KeyboardInterrupt``); yields ``pressed()``, true once
    Ctrl-C was pressed since the block began.

    Parameters
    ----------
    repeat : float, optional
        Seconds after which an interrupt is raised again if the block is still running (and again after
        as long once more): for a program that must stop on Ctrl-C even where a library swallowed it.
        The last repeat may be raised as the block closes.

    Notes
    -----
    Blocks nest. Python's own handler is left in place, and ``pressed()`` stays false, outside the main
    thread or when a program installed a handler of its own.
    """
    previous = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if previous not in (signal.default_int_handler, _record):
        yield lambda: False
        return
    start, token = _PRESSES, object()
    if repeat is not None:
        with _LOCK:
            _REPEATS[token] = float(repeat)
    signal.signal(signal.SIGINT, _record)
    try:
        yield lambda: _PRESSES > start
    finally:
        _uninterrupted(_close, token, previous)


def _close(token, previous) -> None:
    """No more repeats for this block; the handler back to ``previous`` (``signal.signal`` first runs a
    pending handler, so this may raise before it is done: it is safe to repeat)."""
    with _LOCK:
        _REPEATS.pop(token, None)
        if not _REPEATS:
            for timer in _TIMERS:
                timer.cancel()
            _TIMERS.clear()
    signal.signal(signal.SIGINT, previous)


def _uninterrupted(step, *args) -> None:
    """``step(*args)`` to its end (it is idempotent), then the interrupt that arrived meanwhile, if one did."""
    interrupted = False
    while True:
        try:
            step(*args)
            break
        except KeyboardInterrupt:
            interrupted = True
    if interrupted:
        raise KeyboardInterrupt


def interrupt_handled() -> None:
    """Tell CPython that the interrupt was handled, so the program ends with the exit code it returns.

    A ``KeyboardInterrupt`` that ends Python code run by a C extension through ``PyRun_*`` (in CasADi's
    bindings) sets CPython's record of an unhandled interrupt, even when the extension then clears the
    exception; at exit CPython then kills the process with SIGINT whatever code the program returned
    (measured: 3 of 15 interrupted CLI runs under load exited by SIGINT after printing their one line;
    with this, 18 of 18 exited with 130). Running any code through ``PyRun_SimpleString`` resets it.
    """
    if sys.implementation.name == "cpython":
        with contextlib.suppress(Exception):
            ctypes.pythonapi.PyRun_SimpleString(b"pass")


def _command_process() -> bool:
    if os.path.basename(sys.argv[0] if sys.argv else "") == "symsbl":  # the console script
        return True
    orig = getattr(sys, "orig_argv", [])  # python [options] -m symsbl ...
    return any(a == "-m" and b == "symsbl" for a, b in zip(orig, orig[1:]))


def _interrupted_starting(signum, frame):  # noqa: ARG001 - a signal handler's signature
    command = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1].isalpha() else ""
    try:
        os.write(2, f"symsbl{' ' + command if command else ''}: error: interrupted\n".encode())
    finally:
        os._exit(130)


def command_started() -> None:
    """SIGINT back to Python's default handler, if the start-up one is still installed."""
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is _interrupted_starting
    ):
        signal.signal(signal.SIGINT, signal.default_int_handler)


if (
    _command_process()
    and threading.current_thread() is threading.main_thread()
    and signal.getsignal(signal.SIGINT) is signal.default_int_handler
):
    signal.signal(signal.SIGINT, _interrupted_starting)
