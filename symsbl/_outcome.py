"""How a ``symsbl`` command ends: an exit code (:data:`EXIT_CODES`) and at most one line on standard error.

Every failure is one line, ``symsbl <command>: error: <what>``; warnings are one line each, like errors.
After Ctrl-C the one line is ``interrupted`` (exit 130), even where a library on the way turned the
interrupt into another error or swallowed it (:func:`symsbl._base.interrupt.sigint_recorded`): the interrupt
is raised again every :data:`REPEAT_SECONDS` while the command still runs.
"""

from __future__ import annotations

import contextlib
import os
import sys
import traceback
import warnings

from ._base.errors import MissingExtraError, SymsblError
from ._base.interrupt import interrupt_handled, sigint_recorded
from ._base.progress import progress_enabled

__all__ = ["EXIT_CODES", "REPEAT_SECONDS", "fail", "run_command"]

#: Exit codes of the ``symsbl`` command.
EXIT_CODES = {
    0: "success",
    1: "the model diverged in simulation, or no model was found",
    2: "bad input: arguments, files, data or model (one line on standard error says which)",
    3: "internal error (a bug; SYMSBL_TRACEBACK=1 prints the traceback)",
    130: "interrupted (Ctrl-C)",
}

#: Seconds after Ctrl-C at which a command still running is interrupted again.
REPEAT_SECONDS = 0.5

_INTERRUPTED = (130, "interrupted")

#: What takes less memory, by command.
_LIGHTER = {
    "identify": "use a shorter record, fewer candidate terms or a lower --degree (without it, 4 is tried beside 3)",
    "discrepancy": "use a shorter record or --no-library",
    "validate": "use a shorter record or fewer --band draws",
    "simulate": "use a shorter record or fewer --band draws",
    "demo": "use --quick",
}


def fail(command: str, message: str, code: int) -> int:
    """Print ``symsbl <command>: error: <message>`` on standard error (if it is still open); return ``code``."""
    with contextlib.suppress(OSError, ValueError):
        print(f"symsbl {command}: error: {message}", file=sys.stderr)
    return code


def run_command(command: str, work, quiet: bool = False) -> int:
    """``work()`` (which returns the exit code) with every failure, and Ctrl-C, as one line on standard error.

    A reader of standard output that leaves early (``symsbl identify ... | head -3``) does not stop the work:
    what is printed after it left is dropped, the files are still written.
    """
    try:
        with sigint_recorded(repeat=REPEAT_SECONDS) as pressed, _reader_may_leave():
            code, message = _outcome(command, work, quiet, pressed)
            if pressed():  # whatever a library on the way made of the interrupt
                code, message = _INTERRUPTED
    except KeyboardInterrupt:  # raised again as the block closed
        code, message = _INTERRUPTED
    if code == _INTERRUPTED[0]:
        interrupt_handled()
    return code if message is None else fail(command, message, code)


class _Stdout:
    """Standard output that goes on, into /dev/null, once its reader has left (EPIPE)."""

    def __init__(self, stream):
        self._stream = stream

    def _left(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())  # the buffered text, and what follows, goes nowhere
        os.close(devnull)

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._left()
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._left()

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _reader_may_leave():
    """Standard output as :class:`_Stdout` inside the block (when it is a file descriptor: a pipe, a terminal)."""
    stream = sys.stdout
    try:
        stream.fileno()
    except Exception:  # noqa: BLE001 - captured or replaced output: nothing to guard
        yield
        return
    guarded = _Stdout(stream)
    sys.stdout = guarded
    try:
        yield
    finally:
        guarded.flush()
        if sys.stdout is guarded:
            sys.stdout = stream


def _warning_line(command: str, pressed):
    """Warnings as one line on standard error, like errors: ``symsbl <command>: warning: <message>``; none once
    ``pressed()`` (after Ctrl-C the one line is "interrupted")."""

    def show(message, category, filename, lineno, file=None, line=None):
        if not pressed():
            print(f"symsbl {command}: warning: {' '.join(str(message).split())}", file=sys.stderr)

    return show


def _outcome(command: str, work, quiet: bool, pressed) -> tuple[int, str | None]:
    """The exit code of ``work()`` and the line to print (None: nothing)."""
    try:
        with progress_enabled(False) if quiet else contextlib.nullcontext(), warnings.catch_warnings():
            warnings.showwarning = _warning_line(command, pressed)
            return work(), None
    except KeyboardInterrupt:
        return _INTERRUPTED
    except (SymsblError, MissingExtraError) as exc:
        return 2, " ".join(str(exc).split())
    except MemoryError:
        return 2, "out of memory: " + _LIGHTER.get(command, _LIGHTER["identify"])
    except Exception as exc:  # noqa: BLE001 - a bug: one line, after the traceback when asked for it
        if os.environ.get("SYMSBL_TRACEBACK") and not pressed():
            with contextlib.suppress(OSError, ValueError):
                traceback.print_exc(file=sys.stderr)
            return 3, f"internal error ({type(exc).__name__}: {' '.join(str(exc).split())[:200]}); please report it"
        return 3, (
            f"internal error ({type(exc).__name__}: {' '.join(str(exc).split())[:200]}); "
            "rerun with SYMSBL_TRACEBACK=1 and report it"
        )
