"""Numbers with their uncertainty, and term names, as people read them: ``1.0002e4(3) x1 |x2|``."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["format_uncertain", "pretty"]


def format_uncertain(value: float, std: float, signed: bool = False) -> str:
    """Format ``value`` with its standard deviation in parentheses, e.g. ``1.000(0.001)``.

    The value is printed to the digit of the standard deviation's leading figure; values of
    magnitude >= 1e4 or < 1e-3 use an exponent, e.g. ``1.0002e4(3)``.

    Parameters
    ----------
    value, std : float
        Mean and standard deviation.
    signed : bool
        Print as a continuation term: ``+ v(s)`` or ``- v(s)``.
    """
    sign = "-" if value < 0 else ""
    v = abs(value)
    if signed:
        sign = "- " if value < 0 else "+ "
    if not np.isfinite(std) or std <= 0:
        return f"{sign}{v:.6g}"
    exp_v = math.floor(math.log10(v)) if v > 0 else 0
    exp_s = math.floor(math.log10(std))
    digits = int(min(max(exp_v - exp_s + 1, 1), 8))
    if v >= 1e4 or (0 < v < 1e-3):
        mant = round(v / 10**exp_v, digits - 1)
        if mant >= 10:  # rounding carried into the next decade
            exp_v += 1
            mant /= 10
        return f"{sign}{mant:.{digits - 1}f}e{exp_v}({_one_figure(std)})"
    decimals = max(-exp_s, 0)
    return f"{sign}{v:.{decimals}f}({_one_figure(std)})"


def _one_figure(std: float) -> str:
    if 1e-3 <= std < 1e4:
        decimals = max(-math.floor(math.log10(std)), 0)
        return f"{std:.{decimals}f}"
    return f"{std:.0e}".replace("e+0", "e").replace("e-0", "e-").replace("e+", "e")


def pretty(name: str) -> str:
    """A term name with ``**`` as ``^``, ``*`` as a space and ``Abs(x)`` as ``|x|``."""
    text = name.replace("**", "^").replace("*", " ")
    while "Abs(" in text:
        i = text.index("Abs(")
        depth, j = 0, i + 3
        for j in range(i + 3, len(text)):
            depth += {"(": 1, ")": -1}.get(text[j], 0)
            if depth == 0:
                break
        text = text[:i] + "|" + text[i + 4 : j] + "|" + text[j + 1 :]
    return text
