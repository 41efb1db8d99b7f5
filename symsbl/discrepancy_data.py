"""Inputs of the discrepancy workflow: the base model spec, noise levels, position records."""

from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np
import sympy as sp

from .data import Trajectory, noise_levels
from .errors import DataError, LibraryError
from .symbolic import sympy_to_casadi

__all__ = ["parse_base", "noise_levels", "position_record"]


def parse_base(text: str, state_names: Sequence[str], input_names: Sequence[str] = ()) -> dict[str, tuple]:
    """Read a model structure such as ``"x1: x2; x2: F, x1, x2"``.

    Parameters
    ----------
    text : str
        Per state, ``state: term, term, ...``, states separated by ``;``. Terms are expressions
        of the state and input names (sympy syntax: ``x2*Abs(x2)``, ``sign(v)``); ``1`` is a
        constant offset. Every state needs an equation.
    state_names, input_names : sequence of str

    Returns
    -------
    dict
        State name -> tuple of casadi.SX terms, in state order.

    Raises
    ------
    LibraryError
        Naming the part of ``text`` that is wrong.
    """
    symbols = {n: ca.SX.sym(n) for n in list(state_names) + list(input_names)}
    local = {n: sp.Symbol(n, real=True) for n in symbols}
    local.update({"sign": sp.sign, "Abs": sp.Abs, "abs": sp.Abs})
    out: dict[str, list] = {}
    for part in filter(None, (p.strip() for p in str(text).split(";"))):
        lhs, sep, rhs = part.partition(":")
        lhs = lhs.strip()
        if not sep or not rhs.strip():
            raise LibraryError(
                f"--base: expected 'state: term, term' for each state, separated by ';'; received {part!r}."
            )
        if lhs not in state_names:
            raise LibraryError(f"--base: {lhs!r} is not a state; the states are {list(state_names)}.")
        if lhs in out:
            raise LibraryError(f"--base: state {lhs!r} has two equations; give each state one 'state: terms' part.")
        terms = []
        for raw in filter(None, (r.strip() for r in rhs.split(","))):
            try:
                expr = sp.sympify(raw, locals=local)
            except (sp.SympifyError, SyntaxError, TypeError, AttributeError):
                raise LibraryError(f"--base: cannot read the term {raw!r} of state {lhs!r}.") from None
            unknown = sorted(str(s) for s in expr.free_symbols if str(s) not in symbols)
            if unknown:
                raise LibraryError(
                    f"--base: the term {raw!r} of state {lhs!r} uses {unknown}, which are not among the "
                    f"states {list(state_names)} or inputs {list(input_names)}."
                )
            terms.append(ca.SX(1) if expr.is_number else sympy_to_casadi(expr, symbols))
        out[lhs] = terms
    missing = [s for s in state_names if s not in out]
    if missing:
        raise LibraryError(f"--base: no terms for the states {missing}; give every state 'state: terms'.")
    return {s: tuple(out[s]) for s in state_names}


def position_record(t, position, inputs, *, cutoff: float, names=("q", "v"), input_names=("tau",)) -> Trajectory:
    """A (position, velocity) record from a measured position, for inverse models.

    The position is low-passed by a zero-phase 4th-order Butterworth filter at ``cutoff`` Hz
    (an encoder's quantisation is white above the motion's band) and differentiated by
    central differences; the weak form then differentiates the velocity once more.
    This is the recipe of the EMPS benchmark (Janot et al., 2019), which uses 100 Hz.

    Parameters
    ----------
    t : array_like, shape (n_samples,)
    position : array_like, shape (n_samples,)
    inputs : array_like, shape (n_samples,) or (n_samples, n_inputs)
    cutoff : float
        Filter cut-off in Hz, below the Nyquist frequency.
    names, input_names : tuple of str
    """
    from scipy.signal import butter, filtfilt

    t = np.asarray(t, dtype=float)
    nyquist = 0.5 / float(np.mean(np.diff(t)))
    if not 0 < cutoff < nyquist:
        raise DataError(f"cutoff must be in (0, {nyquist:g}) Hz (the Nyquist frequency); received {cutoff!r}.")
    b, a = butter(4, cutoff / nyquist)
    q = filtfilt(b, a, np.asarray(position, dtype=float))
    return Trajectory(t, np.column_stack([q, np.gradient(q, t)]), inputs, tuple(names), tuple(input_names))


# ---------------------------------------------------------------------------------- results


def _split(data: Trajectory, fraction: float = 0.7) -> tuple[Trajectory, Trajectory]:
    cut = int(fraction * data.n_samples)
    return data.slice(0, cut), data.slice(cut, None)


def _check_traj(traj, what, names):
    if not isinstance(traj, Trajectory):
        raise DataError(f"{what} must be a Trajectory; received {type(traj).__name__}.")
    if names is not None and (tuple(traj.state_names), tuple(traj.input_names)) != names:
        raise DataError(
            f"{what} must have the training record's states {list(names[0])} and inputs {list(names[1])}; "
            f"received {list(traj.state_names)} and {list(traj.input_names)}."
        )
