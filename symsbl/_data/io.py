"""Reading and writing records and results: CSV (the dialects lab software exports), ``.npz``, ``.mat``.

Input files are only ever opened for reading; outputs go through :mod:`symsbl._base.outputs`.

CSV dialects understood (detected, never configured): a UTF-8 byte-order mark, ``,``, ``;`` or
tab separators, decimal commas with ``;`` or tab separators, ``#`` comment lines anywhere, a
units row under the header (a row with no number in it), blank lines, quoted cells. Duplicate
header names are an error when the column is asked for, naming both positions.
"""

from __future__ import annotations

import codecs
import contextlib
import csv
import io
import math
import os
import re
import stat
import zipfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import cast

import numpy as np

from .._base.errors import DataError, expected
from .._base.outputs import safe_output, write_atomic
from .trajectory import Trajectory, check_magnitude, validate

__all__ = ["read_trajectory", "write_trajectory", "read_columns", "columns_trajectory", "column_names", "FORMATS"]

_MATLAB_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,62}$")
_DECIMAL_COMMA = re.compile(r"^\s*[+-]?(\d+,\d*|,\d+)([eE][+-]?\d+)?\s*$")


# ------------------------------------------------------------------------------------------- CSV


#: Byte-order marks of a spreadsheet's "Unicode text" export (UTF-16) and of UTF-32, longest first.
_BOMS = (
    (codecs.BOM_UTF32_LE, "utf-32"),
    (codecs.BOM_UTF32_BE, "utf-32"),
    (codecs.BOM_UTF16_LE, "utf-16"),
    (codecs.BOM_UTF16_BE, "utf-16"),
)


def _decode(path: Path, raw: bytes) -> str:
    codec = next((name for bom, name in _BOMS if raw.startswith(bom)), None)
    head = raw[:4096]
    if codec is None and b"\x00" in head and not len(raw) % 2 and all(head[0::2]) != all(head[1::2]):
        codec = "utf-16-le" if not any(head[1::2]) else "utf-16-be" if not any(head[0::2]) else None  # no mark
    if codec is not None:
        with contextlib.suppress(UnicodeDecodeError):
            text = raw.decode(codec)
            if "\x00" not in text:
                return text
    if b"\x00" in raw:
        raise DataError(
            expected(
                str(path),
                "a text CSV file",
                "binary content (NUL bytes)",
                "export the record as CSV text, .npz or .mat",
                raw=True,
            )
        )
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("cp1252", errors="replace")  # Windows exports; unknown bytes become U+FFFD


def _delimiter(header: str) -> str:
    counts = {d: header.count(d) for d in (",", ";", "\t")}
    best = max(counts, key=lambda d: (counts[d], d == ","))
    return best if counts[best] else ","


def _number_cells(cells: Sequence[str], decimal_comma: bool) -> list[float] | None:
    """The cells as floats, or None if any is not a number."""
    out = []
    for cell in cells:
        text = cell.strip()
        if decimal_comma and _DECIMAL_COMMA.match(text):
            text = text.replace(",", ".")
        try:
            out.append(float(text))
        except ValueError:
            return None
    return out


def _csv_rows(path: Path, raw: bytes) -> tuple[list[str], list[tuple[int, list[str]]], str]:
    """Header, numbered data rows and the delimiter of a CSV file; comments, units and blanks removed."""
    text = _decode(path, raw)
    lines = [
        (i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise DataError(expected(str(path), "a header row of column names", "an empty file", raw=True))
    delim = _delimiter(lines[0][1])
    try:
        parsed = [(no, row) for no, line in lines for row in csv.reader(io.StringIO(line), delimiter=delim)]
    except csv.Error as err:
        raise DataError(expected(str(path), "CSV text", f"unreadable CSV ({err})", raw=True)) from None
    (_, header), rows = parsed[0], parsed[1:]
    return [h.strip() for h in header], rows, delim


def _read_csv(path: Path, raw: bytes) -> dict[str, np.ndarray]:
    header, rows, delim = _csv_rows(path, raw)
    decimal_comma = delim != ","

    def _numbers(cells):
        return sum(_number_cells([c], decimal_comma) is not None for c in cells if c.strip())

    if len(rows) > 1 and _numbers(rows[0][1]) == 0 < _numbers(rows[1][1]):
        rows = rows[1:]  # a units row: "s, m, m/s, N"
    while header and not header[-1] and all(len(r) >= len(header) and not r[len(header) - 1].strip() for _, r in rows):
        header = header[:-1]  # an empty column after a trailing delimiter on every line
    width = len(header)
    values = np.empty((len(rows), width))
    bad: dict[int, str] = {}  # the first cell that is not a number, by column: an error only if the column is used
    for k, (lineno, row) in enumerate(rows):
        if len(row) > width and not any(c.strip() for c in row[width:]):
            row = row[:width]  # a trailing delimiter on data lines only
        if len(row) != width:
            raise DataError(
                expected(
                    f"{path}: line {lineno}",
                    f"{width} fields, one per header column",
                    f"{len(row)} field{'s' * (len(row) != 1)}",
                    "every row needs one value per column",
                    raw=True,
                )
            )
        numbers = _number_cells(row, decimal_comma)
        if numbers is None:
            cells = [_number_cells([c], decimal_comma) for c in row]
            for j in (j for j, v in enumerate(cells) if v is None and j not in bad):
                bad[j] = expected(
                    f"{path}: column {header[j]!r} at line {lineno}",
                    "a number",
                    row[j].strip() or "an empty cell",
                    "repair or remove the row",
                    raw=not row[j].strip(),
                )
            numbers = [math.nan if v is None else v[0] for v in cells]
        values[k] = numbers
    columns = _named_columns(path, header, values.T)
    if bad:
        columns[_INVALID] = {header[j]: message for j, message in bad.items()}  # type: ignore[assignment]
    return columns


def _named_columns(path: Path, names: Sequence[str], columns) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    seen: dict[str, list[int]] = {}
    for pos, (name, col) in enumerate(zip(names, columns), start=1):
        seen.setdefault(name, []).append(pos)
        out[name] = col
    dupes = {n: p for n, p in seen.items() if len(p) > 1}
    if dupes:
        out[_DUPLICATES] = dupes  # type: ignore[assignment]
    return out


_DUPLICATES = "\x00duplicates"
_INVALID = "\x00invalid"  # columns with a cell that is not a number: the error to raise if one is used


# ------------------------------------------------------------------------------------ npz and mat


def _read_npz(path: Path, raw: bytes | None) -> dict[str, np.ndarray]:
    source = path if raw is None else io.BytesIO(raw)
    if not zipfile.is_zipfile(source):
        raise DataError(
            expected(
                str(path),
                "a readable .npz file (a zip archive written by numpy.savez)",
                "a file that is not a zip archive",
                raw=True,
            )
        )
    if isinstance(source, io.BytesIO):
        source.seek(0)
    try:
        with np.load(source, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except Exception as err:  # noqa: BLE001 - any failure of a foreign file is a data error
        raise DataError(expected(str(path), "a readable .npz file (numpy.savez)", _reason(err), raw=True)) from None


def _read_mat(path: Path, raw: bytes | None) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    try:
        content = loadmat(str(path) if raw is None else io.BytesIO(raw))
    except Exception as err:  # noqa: BLE001 - scipy raises many kinds on corrupt files
        raise DataError(
            expected(
                str(path),
                "a readable MATLAB .mat file (v4-v7.2)",
                _reason(err),
                "save with -v7 or export CSV",
                raw=True,
            )
        ) from None
    return {k: np.asarray(v) for k, v in content.items() if not k.startswith("__")}


def _reason(err: BaseException) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    return f"an unreadable file ({type(err).__name__}{': ' + text[:120] if text else ''})"


def _write_csv(columns: Mapping[str, np.ndarray], fh) -> None:
    for name in columns:
        if any(ch in name for ch in ',"\n\r'):
            raise DataError(expected("column name", "a name without commas, quotes or newlines for CSV", name))
    table = np.column_stack(list(columns.values()))
    np.savetxt(fh, table, fmt="%.17g", delimiter=",", header=",".join(columns), comments="")


def _write_npz(columns: Mapping[str, np.ndarray], fh) -> None:
    np.savez(fh, **columns)  # type: ignore[arg-type]


def _write_mat(columns: Mapping[str, np.ndarray], fh) -> None:
    from scipy.io import savemat

    for name in columns:
        if not _MATLAB_NAME.match(name):
            raise DataError(
                expected(
                    "column name",
                    "a MATLAB variable name (a letter, then letters, digits or underscores, at most 63 characters)",
                    name,
                    "rename it or write .csv/.npz",
                )
            )
    savemat(fh, {k: np.asarray(v)[:, None] for k, v in columns.items()})


#: Readers and writers by file extension.
FORMATS: dict[str, tuple[Callable, Callable]] = {
    ".csv": (_read_csv, _write_csv),
    ".npz": (_read_npz, _write_npz),
    ".mat": (_read_mat, _write_mat),
}


def _format(path: Path):
    try:
        return FORMATS[path.suffix.lower()]
    except KeyError:
        raise DataError(
            expected(
                str(path), f"a file ending in one of {sorted(FORMATS)}", f"the extension {path.suffix!r}", raw=True
            )
        ) from None


def read_columns(path: str | Path) -> dict[str, np.ndarray]:
    """Every column of a ``.csv``, ``.npz`` or ``.mat`` file (or a FIFO of one) by name; the file is only read.

    A column with a cell that is not a number is kept aside: reading it (:func:`columns_trajectory`) names
    the cell; an unused one does not stop the others from being read.
    """
    path = Path(path)
    reader, _ = _format(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as err:
        what = "no such file" if isinstance(err, FileNotFoundError) else f"an error opening it ({err.strerror})"
        raise DataError(expected(str(path), "an existing data file", what, raw=True)) from None
    if not (stat.S_ISREG(mode) or stat.S_ISFIFO(mode)):
        what = "a directory" if stat.S_ISDIR(mode) else "a device or socket, not a file"
        raise DataError(expected(str(path), "an existing data file", what, raw=True))
    try:  # a FIFO can be read once: its bytes are read here; a CSV file is read whole anyway
        raw = path.read_bytes() if stat.S_ISFIFO(mode) or reader is _read_csv else None
        return reader(path, raw)
    except PermissionError:
        raise DataError(expected(str(path), "a readable file", "no permission to read it", raw=True)) from None


def column_names(columns: Mapping[str, np.ndarray]) -> list[str]:
    """The names of the columns :func:`read_columns` found, sorted."""
    return sorted(k for k in columns if k not in (_DUPLICATES, _INVALID) and k)


def _vector(columns: Mapping[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    dupes = cast("dict[str, list[int]]", columns.get(_DUPLICATES, {}))
    if name in dupes:
        raise DataError(
            expected(
                f"{path}: column {name!r}",
                "one column of that name",
                f"{len(dupes[name])} columns named {name!r} (positions {dupes[name]})",
                "rename the duplicates in the header",
                raw=True,
            )
        )
    if name not in columns:
        available = column_names(columns)
        raise DataError(
            expected(
                f"{path}: column {name!r}",
                f"a column among {available}",
                "no such column",
                "check --states/--inputs/--time against the header",
                raw=True,
            )
        )
    message = cast("dict[str, str]", columns.get(_INVALID, {})).get(name)
    if message is not None:  # the first cell of the column that is not a number, worded as it was read
        raise DataError(message)
    arr = np.asarray(columns[name])
    if arr.ndim == 2 and 1 in arr.shape:  # MATLAB stores vectors as 1xN or Nx1
        arr = arr.ravel()
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise DataError(
            expected(
                f"{path}: column {name!r}",
                "a real numeric vector (N, 1xN or Nx1)",
                f"shape {arr.shape} and dtype {arr.dtype}",
                raw=True,
            )
        )
    return arr.astype(float)


def _time(columns, time, fs, n, path) -> np.ndarray:
    if fs is not None:
        fs = float(fs) if isinstance(fs, (int, float, np.number)) and not isinstance(fs, bool) else fs
        if not isinstance(fs, float) or not np.isfinite(fs) or fs <= 0:
            raise DataError(expected("fs", "a positive sample rate in Hz", fs))
    if time is None:
        if fs is None:
            raise DataError(
                expected(
                    "fs",
                    "a positive sample rate in Hz when there is no time column",
                    "none",
                    "name the time column, or give the rate (--fs HZ on the command line, fs= in Python)",
                    raw=True,
                )
            )
        return np.arange(n) / fs
    t = _vector(columns, time, path)
    if t.size != n:
        raise DataError(
            expected(
                f"{path}: time column {time!r}", f"{n} samples like the data columns", f"{t.size} samples", raw=True
            )
        )
    if fs is None:
        return t
    # A time column rounded to a coarse resolution: trust fs, check the column agrees with it.
    grid = t[0] + np.arange(n) / fs
    step = float(np.max(np.abs(np.diff(t)))) if n > 1 else 0.0
    worst = float(np.max(np.abs(t - grid))) if n else 0.0
    if not np.isfinite(worst) or worst > max(step, 1.0 / fs):
        raise DataError(
            expected(
                f"{path}: time column {time!r}",
                f"times within one step of a uniform {fs:g} Hz grid (--fs)",
                f"a deviation of {worst:.3g} s",
                "check --fs, or leave it out to use the time column",
                raw=True,
            )
        )
    return grid


def read_trajectory(
    path: str | Path,
    *,
    states: Sequence[str],
    inputs: Sequence[str] = (),
    time: str | None = "t",
    fs: float | None = None,
) -> Trajectory:
    """Read a trajectory from a ``.csv`` (header row), ``.npz`` or ``.mat`` file.

    Parameters
    ----------
    path : str or Path
        The file; it is only read.
    states, inputs : sequence of str
        Column (variable) names to use as states and as inputs, in this order.
    time : str or None
        Name of the time column. ``None`` builds ``t = arange(n) / fs`` instead (then ``fs`` is required).
    fs : float, optional
        Sample rate in Hz. Without a time column it makes the time grid; with one, it replaces a
        column rounded to a coarse resolution (timestamps to 0.1 ms at 32768 Hz) by the uniform
        grid from its first value, after checking that the column stays within a step of it.

    Returns
    -------
    Trajectory

    Raises
    ------
    DataError
        An unsupported extension, an unreadable file, a missing or duplicated column (the message
        lists those available), a column that is not a vector, columns of different lengths, too
        few samples, non-finite values or a time column that is not strictly increasing and
        uniform (row named).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import symsbl
    >>> t = symsbl.time_grid(1.0, 100)
    >>> record = symsbl.Trajectory(t, np.column_stack([np.sin(t), np.cos(t)]), np.cos(3 * t), ("x1", "x2"), ("F",))
    >>> path = os.path.join(tempfile.mkdtemp(), "record.csv")
    >>> symsbl.write_trajectory(record, path)
    >>> back = symsbl.read_trajectory(path, states=["x1", "x2"], inputs=["F"])
    >>> back.state_names, back.input_names, bool(np.allclose(back.states, record.states))
    (('x1', 'x2'), ('F',), True)
    """
    path = Path(path)
    if not tuple(states):
        raise DataError(expected("states", "at least one column name", "an empty list", raw=True))
    return columns_trajectory(read_columns(path), path, states=states, inputs=inputs, time=time, fs=fs)


def columns_trajectory(
    columns: Mapping[str, np.ndarray],
    path: str | Path,
    *,
    states: Sequence[str],
    inputs: Sequence[str] = (),
    time: str | None = "t",
    fs: float | None = None,
) -> Trajectory:
    """The trajectory :func:`read_trajectory` reads, from the columns :func:`read_columns` returned for ``path``
    (a file read once, as a FIFO must be)."""
    path = Path(path)
    state_names, input_names = tuple(states), tuple(inputs)
    if not state_names:
        raise DataError(expected("states", "at least one column name", "an empty list", raw=True))
    data = {name: _vector(columns, name, path) for name in state_names + input_names}
    lengths = {name: v.size for name, v in data.items()}
    if len(set(lengths.values())) > 1:
        raise DataError(expected(str(path), "columns of one length", f"lengths {lengths}", raw=True))
    n = next(iter(lengths.values()))
    t = _time(columns, time, fs, n, path)
    st = np.column_stack([data[k] for k in state_names])
    ip = np.column_stack([data[k] for k in input_names]) if input_names else np.empty((n, 0))
    t, st, ip = validate(t, st, ip, state_names, input_names, source=str(path))
    traj = Trajectory(t, st, ip, state_names, input_names)
    check_magnitude(traj, str(path))
    return traj


def write_trajectory(traj: Trajectory, path: str | Path) -> None:
    """Write ``traj`` to ``.csv`` (``%.17g``, exact round trip), ``.npz`` or ``.mat`` (Nx1 columns).

    The columns are ``t``, the states and the inputs, under their names; read them back with
    ``read_trajectory(path, states=traj.state_names, inputs=traj.input_names)``. The file is
    written to a temporary name and renamed into place.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import symsbl
    >>> t = symsbl.time_grid(1.0, 100)
    >>> record = symsbl.Trajectory(t, np.sin(t)[:, None], None, ("x",))
    >>> path = os.path.join(tempfile.mkdtemp(), "record.npz")
    >>> symsbl.write_trajectory(record, path)
    >>> sorted(np.load(path).files)
    ['t', 'x']
    """
    if not isinstance(traj, Trajectory):
        raise DataError(expected("traj", "a Trajectory", type(traj).__name__, raw=True))
    path = safe_output(path, what="path")
    _, writer = _format(path)
    columns = traj.to_dict()
    if path.suffix.lower() == ".csv":
        write_atomic(path, lambda fh: writer(columns, fh), binary=False)
    else:
        write_atomic(path, lambda fh: writer(columns, fh), suffix=path.suffix)
