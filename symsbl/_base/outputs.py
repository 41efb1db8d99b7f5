"""Writing results safely: never over an input, never half a file, never a special file replaced.

What an output path names decides how it is written (:func:`output_target`):

- a regular file, or a new name in an existing directory, is written to a temporary file beside it
  that is renamed into place, so a failed or interrupted run never leaves a truncated file behind
  and never changes what was there before;
- a symbolic link is followed: its target is replaced that way and the link stays a link; a dangling
  link creates its target, when the target's directory exists;
- a FIFO or a character device (``/dev/null``, a terminal, ``/dev/stdout``) is written through: opened
  and written, never renamed over (as a shell's ``>>`` would);
- an empty path, a directory, a block device, a socket and a loop of links are refused.

:func:`safe_output` checks a path before any work starts (it is none of the inputs, it can be
written); :func:`distinct_outputs` refuses two outputs of one command on the same file;
:func:`write_atomic` writes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import stat
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

from .errors import DataError, expected

__all__ = ["OutputTarget", "output_target", "safe_output", "distinct_outputs", "write_atomic", "same_file"]


@dataclasses.dataclass(frozen=True)
class OutputTarget:
    """Where an output path leads.

    Attributes
    ----------
    path : Path
        The path as given.
    real : Path
        The file written: ``path`` with its symbolic links followed (``path`` itself when written through).
    through : bool
        True for a FIFO or a character device: opened and written, never replaced.
    """

    path: Path
    real: Path
    through: bool


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory")):
        if test(mode):
            return name
    return "a special file"


def output_target(path, *, what: str = "path") -> OutputTarget:
    """Resolve an output path to what will be written.

    Parameters
    ----------
    path : str or Path
        The output, as given by the user.
    what : str
        The option or argument naming it, for messages.

    Returns
    -------
    OutputTarget

    Raises
    ------
    DataError
        ``path`` is empty, a directory, a block device or a socket, a loop of symbolic links, or a
        dangling link whose target's directory is missing.
    """
    if str(path) == "":
        raise DataError(expected(what, "a file path", "''", "name the file to write", raw=True))
    path = Path(path)
    shown = repr(str(path))
    try:
        st = os.stat(path)  # follows links, including /proc's (/dev/stdout)
    except FileNotFoundError:
        st = None
    except OSError as err:  # ELOOP, EACCES on the way, a name too long
        raise DataError(expected(what, "a path that can be opened", f"{shown} ({err.strerror})", raw=True)) from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise DataError(expected(what, "a file path", f"{shown}, which is a directory", raw=True))
    if st is not None and not stat.S_ISREG(st.st_mode):
        if stat.S_ISFIFO(st.st_mode) or stat.S_ISCHR(st.st_mode):
            return OutputTarget(path, path, True)
        raise DataError(
            expected(
                what,
                "a file, a FIFO or a character device",
                f"{shown}, which is {_kind(st.st_mode)}",
                "choose a file name",
                raw=True,
            )
        )
    if st is not None and _via_proc(path):  # /dev/stdout redirected to a file: the open file, not its name
        return OutputTarget(path, path, True)
    real = Path(os.path.realpath(path))
    if st is not None:
        return OutputTarget(path, real, False)
    if not real.parent.is_dir():
        linked = f" (a symbolic link to {str(real)!r})" if path.is_symlink() else ""
        raise DataError(
            expected(
                what,
                "a file in an existing directory",
                f"{shown}{linked}",
                f"create {str(real.parent)!r} first",
                raw=True,
            )
        )
    return OutputTarget(path, real, False)


def _via_proc(path: Path) -> bool:
    """Whether following ``path``'s links passes through /proc (``/dev/stdout``, ``/dev/fd/N``): such a link
    names an open file, which a rename would take from the process holding it."""
    hop = Path(os.path.abspath(path))
    for _ in range(40):
        parent = Path(os.path.realpath(hop.parent))
        if parent.parts[:2] == ("/", "proc"):
            return True
        if not hop.is_symlink():
            return False
        hop = Path(os.path.normpath(parent / os.readlink(hop)))
    return False


def same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name one file (the same path, a hard or a symbolic link)."""
    a, b = Path(a), Path(b)
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def safe_output(path, inputs: Sequence = (), *, what: str = "--json") -> Path:
    """Check, before any work, that ``path`` can be written without touching an input.

    Parameters
    ----------
    path : str or Path
        The output file.
    inputs : sequence of str or Path
        Files the run reads; the output may be none of them (same path, hard link or symbolic link).
    what : str
        The option or argument naming the output, for messages.

    Returns
    -------
    Path

    Raises
    ------
    DataError
        The output is an input, empty, a directory, a block device or a socket, in a missing or
        unwritable directory, or an existing file that cannot be written.
    """
    target = output_target(path, what=what)
    path = target.path
    for src in inputs:
        if src is not None and str(src) != "" and same_file(path, src):
            raise DataError(
                expected(
                    what,
                    "an output file other than the inputs",
                    f"{str(path)!r}, which is the input {str(src)!r}",
                    "choose another file name; inputs are never modified",
                    raw=True,
                )
            )
    if target.through:
        if not os.access(path, os.W_OK):
            raise DataError(expected(what, "a writable location", f"{str(path)!r}, which cannot be written", raw=True))
        return path
    try:  # the only reliable test of a directory: write to it
        with tempfile.TemporaryFile(dir=target.real.parent):
            pass
    except OSError:
        raise DataError(
            expected(what, "a writable location", f"{str(path)!r}, in a directory that cannot be written", raw=True)
        ) from None
    if target.real.exists() and not os.access(target.real, os.W_OK):
        raise DataError(expected(what, "a writable location", f"{str(path)!r}, which is read-only", raw=True))
    return path


def _identity(target: OutputTarget):
    try:
        st = os.stat(target.path)
        return st.st_dev, st.st_ino
    except OSError:
        return str(target.real)


def distinct_outputs(outputs: Sequence[tuple[str, object]]) -> None:
    """Refuse two outputs of one command on the same file (after following links).

    Parameters
    ----------
    outputs : sequence of (str, str or Path or None)
        ``(option, path)`` pairs; a None path is absent.

    Raises
    ------
    DataError
        Two of the paths lead to one file.
    """
    seen: dict = {}
    for what, path in outputs:
        if path is None:
            continue
        key = _identity(output_target(path, what=what))
        if key in seen:
            first, first_path = seen[key]
            same = "" if str(first_path) == str(path) else f" (as {str(first_path)!r})"
            raise DataError(
                expected(
                    what,
                    f"a file other than {first}'s",
                    f"{str(path)!r}, which {first} writes too{same}",
                    "give each output its own file",
                    raw=True,
                )
            )
        seen[key] = (what, path)


def write_atomic(path, write: Callable[[IO[Any]], object], *, binary: bool = True, suffix: str = "") -> None:
    """Write through ``write(file)`` to ``path`` as :func:`output_target` resolves it.

    A file (or a link's target) gets a temporary file beside it, renamed into place: an error or an
    interruption removes the temporary file and leaves the file as it was. A FIFO or a character
    device gets the whole content, rendered first, in one open. ``suffix`` keeps the extension for
    writers that read it (matplotlib's ``savefig``).
    """
    target = output_target(path, what=str(path))
    if target.through:
        _write_through(target.path, write, binary)
        return
    real = target.real
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{real.name}.", suffix=suffix or ".tmp", dir=real.parent)
    except OSError as err:
        raise DataError(
            expected(str(path), "a writable location", f"an error creating it ({err.strerror})", raw=True)
        ) from None
    try:
        with os.fdopen(fd, "wb" if binary else "w") as fh:
            write(fh)
        if real.exists():
            with contextlib.suppress(OSError):
                os.chmod(tmp, real.stat().st_mode & 0o777)
        else:
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, real)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _write_through(path: Path, write: Callable[[IO[Any]], object], binary: bool) -> None:
    """Render the content, then write it to ``path`` in one open: through this process's own standard output
    or error when ``path`` is that file (``/dev/stdout``: after what was printed, at the same offset), else
    opened for appending (as ``>>``)."""
    buffer = io.BytesIO() if binary else io.StringIO()
    write(buffer)
    content = buffer.getvalue()
    data = content.encode() if isinstance(content, str) else content
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    own = _own_stream(path)
    try:
        fd = os.dup(own) if own is not None else os.open(path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_NOCTTY", 0))
    except OSError as err:
        raise DataError(
            expected(str(path), "a writable location", f"an error opening it ({err.strerror})", raw=True)
        ) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
    except BrokenPipeError:
        if own is None:
            raise DataError(
                expected(
                    str(path), "a reader until the end of the output", "a reader that left (broken pipe)", raw=True
                )
            ) from None
        devnull = os.open(os.devnull, os.O_WRONLY)  # our own output's reader left (| head): the rest goes nowhere
        os.dup2(devnull, own)
        os.close(devnull)


def _own_stream(path: Path) -> int | None:
    """The descriptor of this process's standard output or error when ``path`` is the same file, else None."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            fd = stream.fileno()
            if os.path.samestat(os.fstat(fd), st):
                return fd
    return None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
