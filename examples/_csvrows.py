"""Records from CSV files for the examples' readers: each row's cells, and a bad cell named by line and column."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def read_rows(path: Path) -> tuple[list[dict[str, str]], list[int]]:
    """Each row's cells by column name (names and cells stripped), and the line of the file each row ends on."""
    with path.open(newline="", encoding="utf-8-sig") as handle:  # a spreadsheet's byte-order mark is no name
        reader = csv.DictReader(handle)
        rows, lines = [], []  # blank lines are skipped: the line numbers keep counting them
        for row in reader:
            rows.append({k.strip(): (v or "").strip() for k, v in row.items() if k})
            lines.append(reader.line_num)
    return rows, lines


def column(rows: list[dict[str, str]], lines: list[int], name: str) -> np.ndarray:
    """The column ``name`` as numbers."""
    return np.array([number(r[name], line, name) for r, line in zip(rows, lines)])


def number(text: str, line: int, name: str) -> float:
    """The number in the cell of column ``name`` on ``line`` of the file, or one line naming the cell."""
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"line {line}, column {name}: expected a number, received {text!r}") from None
