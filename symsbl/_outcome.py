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


def fail(command: str, message: str, code: int) -> int:
    """Print ``symsbl <command>: error: <message>`` on standard error (if it is still open); return ``code``."""
    with contextlib.suppress(OSError, ValueError):
        print(f"symsbl {command}: error: {message}", file=sys.stderr)
    return code


def run_command(command: str, work, quiet: bool = False) -> int:
    """``work()`` (which returns the exit code) with every failure, and Ctrl-C, as one line on standard error."""
    try:
        with sigint_recorded(repeat=REPEAT_SECONDS) as pressed:
            code, message = _outcome(command, work, quiet, pressed)
            if pressed():  # whatever a library on the way made of the interrupt
                code, message = _INTERRUPTED
    except KeyboardInterrupt:  # raised again as the block closed
        code, message = _INTERRUPTED
    if code == _INTERRUPTED[0]:
        interrupt_handled()
    return code if message is None else fail(command, message, code)


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
        return 2, "out of memory: use a shorter record, fewer candidate terms or a lower --degree"
    except Exception as exc:  # noqa: BLE001 - a bug: one line unless asked for the traceback
        if os.environ.get("SYMSBL_TRACEBACK") and not pressed():
            raise
        return 3, (f"internal error ({type(exc).__name__}: {' '.join(str(exc).split())[:200]}); "
                   "rerun with SYMSBL_TRACEBACK=1 and report it")
