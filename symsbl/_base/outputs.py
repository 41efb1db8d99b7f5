"""Writing results safely: never over an input, never half a file.

A path that is one of the inputs (the same file, a hard link or a symbolic link to it), a
directory, a missing parent or an unwritable location is refused before any work starts
(:func:`safe_output`); the content goes to a temporary file in the target directory that is
renamed into place (:func:`write_atomic`), so a failed or interrupted run never leaves a
truncated file behind and never changes what was there before.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from .errors import DataError, expected

__all__ = ["safe_output", "write_atomic"]


def _same_file(a: Path, b: Path) -> bool:
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
        The output is an input, a directory, in a missing or unwritable directory, or an
        existing file that cannot be replaced.
    """
    path = Path(path)
    for src in inputs:
        if src is not None and _same_file(path, Path(src)):
            raise DataError(expected(what, "an output file other than the inputs", f"{str(path)!r}, which is the "
                                     f"input {str(src)!r}", "choose another file name; inputs are never modified",
                                     raw=True))
    if path.is_dir():
        raise DataError(expected(what, "a file path", f"{str(path)!r}, which is a directory", raw=True))
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise DataError(expected(what, "a file in an existing directory", f"{str(path)!r}",
                                 f"create {str(parent)!r} first", raw=True))
    try:  # the only reliable test of a directory: write to it
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError:
        raise DataError(expected(what, "a writable location", f"{str(path)!r}, in a directory that cannot be "
                                 "written", raw=True)) from None
    if path.exists() and not os.access(path, os.W_OK):
        raise DataError(expected(what, "a writable location", f"{str(path)!r}, which is read-only", raw=True))
    return path


def write_atomic(path, write: Callable[[object], None], *, binary: bool = True, suffix: str = "") -> None:
    """Write through ``write(file)`` to a temporary file beside ``path``, then rename it into place.

    An error or an interruption removes the temporary file and leaves ``path`` as it was.
    ``suffix`` keeps the extension for writers that read it (matplotlib's ``savefig``).
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or ".tmp", dir=path.parent or ".")
    except OSError as err:
        raise DataError(expected(str(path), "a writable location", f"an error creating it ({err.strerror})",
                                 raw=True)) from None
    try:
        with os.fdopen(fd, "wb" if binary else "w") as fh:
            write(fh)
        if path.exists():
            with contextlib.suppress(OSError):
                os.chmod(tmp, path.stat().st_mode & 0o777)
        else:
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
