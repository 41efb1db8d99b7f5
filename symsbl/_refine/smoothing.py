"""Fitting through a sign: ``sign(a)`` is fitted as ``tanh(a / eps)`` where a term jumps across ``a = 0``.

Fixed-step RK4 of a term that jumps is discontinuous in its coefficients, and the Gauss-Newton curvature of
such a fit is about twice too large; a ``tanh`` of a small width ``eps`` is continuous and simulates the same
response to within the width. The model returned keeps ``sign``.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import sympy as sp

from .._model import IdentifiedModel, TermEstimate
from .._symbolic.symbols import sympy_to_casadi

__all__ = ["smoothing_widths", "sign_jumps", "smooth_model", "width_of"]


def smoothing_widths(model: IdentifiedModel, records, guess: np.ndarray | None = None) -> dict:
    """Per state, the width ``eps`` of ``tanh(x / eps)`` that stands for ``sign(x)`` while fitting: about 3e-4
    of the state's standard deviation (in the records, else in the ``guess`` of every state, ``(n_total,
    n_states)``, where it is not zero), rounded to a power of two."""
    widths = {}
    for k, name in enumerate(model.state_names):
        cols = [r.column(name) for r in records if name in r.state_names]
        if not cols and guess is not None and np.any(guess[:, k]):
            cols = [guess[:, k]]
        scale = float(np.std(np.concatenate(cols))) if cols else 1.0
        # on a grid of powers of two: records of similar scale (folds, windows, bootstrap copies) give the same
        # expressions and so share one compiled function
        widths[name] = 2.0 ** round(math.log2(3e-4 * (scale if scale > 0 else 1.0)))
    return widths


def width_of(expr: sp.Expr, widths: dict) -> float:
    names = sorted(str(s) for s in expr.free_symbols)
    return max((widths.get(n, 1.0) for n in names), default=1.0)


@functools.lru_cache(maxsize=1024)
def sign_jumps(expr: sp.Expr) -> tuple[tuple[sp.Expr, sp.Expr], ...]:
    """Each ``sign(a)`` of ``expr`` across which ``expr`` jumps, with half the jump at ``a = 0``.

    ``sign(x) max(0, |x| - g)`` (a clearance) is continuous: it has no jump and needs no smoothing; ``sign(v)``
    jumps by 2, ``x sign(v)`` by ``2 |x|``. An argument that cannot be solved for zero counts as a jump of the
    sign itself. Cached: every engine of a search asks again about the same terms.
    """
    out = []
    for atom in sorted(expr.atoms(sp.sign), key=sp.default_sort_key):
        arg = atom.args[0]
        half = (expr.subs(atom, 1) - expr.subs(atom, -1)) / 2
        if arg.is_Symbol:
            half = half.subs(arg, 0)
        else:
            symbol = min(arg.free_symbols, key=sp.default_sort_key) if arg.free_symbols else None
            roots = sp.solve(arg, symbol) if symbol is not None else []
            half = half.subs(symbol, roots[0]) if roots else sp.Integer(1)
        half = sp.simplify(half)
        if half != 0:
            out.append((atom, half))
    return tuple(out)


def smooth_model(model: IdentifiedModel, widths: dict) -> IdentifiedModel:
    """The model with ``sign(a)`` replaced by ``tanh(a / eps)`` where the term jumps across ``a = 0``: continuous
    in its coefficients when simulated with fixed steps, so Gauss-Newton sees a calibrated curvature. A sign
    whose term is continuous (a clearance's ``sign(x) max(0, |x| - g)``) is kept: smoothing it would only add
    stiffness."""
    symbols = {s.name(): s for s in model.states + model.inputs}

    def smooth(t: TermEstimate) -> TermEstimate:
        jumps = sign_jumps(t.sympy)
        if not jumps:
            return t
        tanh = {atom: sp.tanh(atom.args[0] / sp.Float(width_of(atom.args[0], widths))) for atom, _ in jumps}
        return dataclasses.replace(t, expr=sympy_to_casadi(t.sympy.xreplace(tanh), symbols))

    equations = tuple(dataclasses.replace(eq, terms=tuple(smooth(t) for t in eq.terms)) for eq in model.equations)
    return dataclasses.replace(model, equations=equations)
