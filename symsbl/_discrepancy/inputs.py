"""Inputs of the discrepancy workflow: the base model spec, noise levels, position records."""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from .._base.errors import DataError, ExpressionError, LibraryError, expected
from .._data.trajectory import Trajectory
from .._symbolic.library import MAX_FILE_NODES, MAX_FILE_TERMS, bound_size, expression_nodes
from .._symbolic.parse import parse_expression
from .._symbolic.symbols import casadi_to_sympy
from .catalogue import Effect

__all__ = ["parse_base", "read_effects", "describe_effects", "position_record", "split_record", "check_record"]


def parse_base(text: str, state_names: Sequence[str], input_names: Sequence[str] = ()) -> dict[str, tuple]:
    """Read a model structure such as ``"x1: x2; x2: F, x1, x2"``, as data (nothing is evaluated).

    Parameters
    ----------
    text : str
        Per state, ``state: term, term, ...``, states separated by ``;``. Terms are expressions
        of the state and input names in the grammar of model files (``x2*Abs(x2)``, ``sign(v)``,
        ``x1**3``); ``1`` is a constant offset. Every state needs an equation.
    state_names, input_names : sequence of str

    Returns
    -------
    dict
        State name -> tuple of casadi.SX terms, in state order.

    Raises
    ------
    LibraryError
        Naming the part of ``text`` that is wrong.

    Examples
    --------
    >>> import symsbl
    >>> base = symsbl.parse_base("x1: x2; x2: F, x1, x2*Abs(x2)", ["x1", "x2"], ["F"])
    >>> {state: [str(t) for t in symsbl.casadi_to_sympy(list(terms))] for state, terms in base.items()}
    {'x1': ['x2'], 'x2': ['F', 'x1', 'x2*Abs(x2)']}
    """
    if not isinstance(text, str):
        raise LibraryError(expected("--base", "text such as 'x1: x2; x2: F, x1, x2'", type(text).__name__, raw=True))
    symbols = {n: ca.SX.sym(n) for n in list(state_names) + list(input_names)}
    out: dict[str, list] = {}
    for part in filter(None, (p.strip() for p in text.split(";"))):
        lhs, sep, rhs = part.partition(":")
        lhs = lhs.strip()
        if not sep or not rhs.strip():
            raise LibraryError(expected("--base", "'state: term, term' for each state, separated by ';'", part))
        if lhs not in state_names:
            raise LibraryError(expected("--base", f"equations of the states {list(state_names)}", lhs))
        if lhs in out:
            raise LibraryError(expected("--base", "one 'state: terms' part per state", f"two for {lhs!r}", raw=True))
        terms = []
        for raw in filter(None, (r.strip() for r in rhs.split(","))):
            try:
                expr = parse_expression(raw, symbols, where=f"--base (state {lhs!r})")
            except ExpressionError as err:
                raise LibraryError(str(err)) from None
            terms.append(ca.SX(1) if expr.is_constant() else expr)
        out[lhs] = terms
    missing = [s for s in state_names if s not in out]
    if missing:
        raise LibraryError(expected("--base", "terms for every state", f"none for {missing}", raw=True))
    return {s: tuple(out[s]) for s in state_names}


def _bounded(count: int, most: int, what: str, path) -> None:
    """Refuse an effects file bringing more than a model file may hold."""
    bound_size(
        count,
        most,
        what,
        where=f"--effects {path}",
        why="the most a model file holds: every effect is scored as a candidate term",
        fix="use fewer or smaller effects",
        error=LibraryError,
    )


def read_effects(path) -> tuple:
    """User effects from a text file, one per line: ``name: expression`` in the displacement ``x`` and the
    velocity ``v`` of a pair, optionally followed by ``; dissipative`` (the force must oppose the motion, as
    friction or damping). Blank lines and ``#`` comments are skipped. Nothing is evaluated.

    Examples
    --------
    A file with the lines ``stribeck: sign(v)*exp(-(v/0.01)**2); dissipative`` and ``tanh_spring: tanh(x/0.002)``
    gives two effects named ``stribeck`` and ``tanh_spring``.

    Raises
    ------
    LibraryError
        Naming the file, the line and what is wrong; or the file, when it holds more effects or expression nodes
        than a model file may (:data:`~symsbl._symbolic.library.MAX_FILE_TERMS`,
        :data:`~symsbl._symbolic.library.MAX_FILE_NODES`).
    """
    import re
    from pathlib import Path

    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise LibraryError(
            expected(
                "--effects", "a readable text file of 'name: expression' lines", str(path), type(err).__name__, raw=True
            )
        ) from None
    entries = [(number, raw) for number, raw in enumerate(lines, 1) if raw.split("#", 1)[0].strip()]
    _bounded(len(entries), MAX_FILE_TERMS, "effects", path)
    x, v = ca.SX.sym("x"), ca.SX.sym("v")
    out, exprs = [], []
    for number, raw in entries:
        text = raw.split("#", 1)[0].strip()
        where = f"--effects {path}, line {number}"
        name, sep, rest = text.partition(":")
        name = name.strip()
        body, _, flag = rest.partition(";")
        if not sep or not re.fullmatch(r"[A-Za-z_]\w*", name) or not body.strip():
            raise LibraryError(
                expected(
                    where,
                    "'name: expression' with a Python-style name, e.g. "
                    "'stribeck: sign(v)*exp(-(v/0.01)**2); dissipative'",
                    raw,
                )
            )
        if flag.strip() not in ("", "dissipative"):
            raise LibraryError(expected(where, "nothing or '; dissipative' after the expression", flag.strip()))
        try:
            expr = parse_expression(body.strip(), {"x": x, "v": v}, where=where)
        except ExpressionError as err:
            raise LibraryError(str(err)) from None
        exprs.append(expr)
        out.append(
            Effect(
                name,
                f"user effect {body.strip()}",
                "user",
                lambda xs, vs, e=expr: ca.substitute(e, ca.vertcat(x, v), ca.vertcat(xs, vs)),
                sign=-1 if flag.strip() else 0,
                coefficient="k",
            )
        )
    if not out:
        raise LibraryError(expected("--effects", "at least one 'name: expression' line", f"none in {path}", raw=True))
    _bounded(expression_nodes(exprs), MAX_FILE_NODES, "expression nodes", path)
    return tuple(out)


def describe_effects(effects) -> str:
    """The catalogue as a table: name, family, term in ``x`` and ``v``, sign rule, description."""
    x, v = ca.SX.sym("x"), ca.SX.sym("v")
    rows = []
    for e in effects:
        variants = e.variants(x, v, 1.0, 1.0)
        terms = ", ".join(str(t) for t in casadi_to_sympy(list(variants[0].exprs)))
        if e.grid:
            terms += f" (g from {e.grid[0]:g} to {e.grid[-1]:g} of the {e.grid_of} amplitude)"
        rule = "must dissipate" if e.sign == -1 else "either sign"
        rows.append(f"{e.name:22s} {e.family:10s} {terms:52s} {rule:15s} {e.description}")
    header = (
        f"{'effect':22s} {'family':10s} {'term (x: displacement, v: velocity)':52s} {'coefficient':15s} description"
    )
    return "\n".join([header] + rows)


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

    Examples
    --------
    A quantised encoder reading of a 1 Hz motion at 1 kHz:

    >>> import numpy as np
    >>> import symsbl
    >>> t = np.arange(2000) / 1000.0
    >>> q = np.round(np.sin(2 * np.pi * t) / 1e-4) * 1e-4          # 0.1 mm encoder steps
    >>> record = symsbl.position_record(t, q, np.cos(t), cutoff=20.0)
    >>> v = record.column("v")[100:-100]
    >>> bool(np.max(np.abs(v - 2 * np.pi * np.cos(2 * np.pi * t[100:-100]))) < 0.05)
    True
    """
    from scipy.signal import butter, filtfilt

    t = np.asarray(t, dtype=float)
    nyquist = 0.5 / float(np.mean(np.diff(t)))
    if not isinstance(cutoff, (int, float)) or not 0 < cutoff < nyquist:
        raise DataError(expected("cutoff", f"a frequency in (0, {nyquist:g}) Hz (the Nyquist frequency)", cutoff))
    b, a = butter(4, cutoff / nyquist)
    q = filtfilt(b, a, np.asarray(position, dtype=float))
    return Trajectory(t, np.column_stack([q, np.gradient(q, t)]), inputs, tuple(names), tuple(input_names))


def split_record(data: Trajectory, fraction: float = 0.7) -> tuple[Trajectory, Trajectory]:
    """The first ``fraction`` of a record for training, the rest held out."""
    cut = int(fraction * data.n_samples)
    return data.slice(0, cut), data.slice(cut, None)


def check_record(traj, what, names):
    """Refuse anything but a Trajectory with the training record's names."""
    if not isinstance(traj, Trajectory):
        raise DataError(expected(what, "a Trajectory", type(traj).__name__, raw=True))
    if names is not None and (tuple(traj.state_names), tuple(traj.input_names)) != names:
        raise DataError(
            expected(
                what,
                f"the training record's states {list(names[0])} and inputs {list(names[1])}",
                f"{list(traj.state_names)} and {list(traj.input_names)}",
                raw=True,
            )
        )
