"""Candidate laws of a latent state, their weak form on a periodic record, and their sparse screening.

- :func:`homogeneous_terms`: the library terms a latent state can use. Its scale is a convention
  (the coefficient of the latent state in the force balance), so only terms that keep their form
  under ``z -> s z`` are meaningful: products of powers and absolute values, and signs (the
  |x|-augmented polynomials of Eq. 21, which hold the Bouc-Wen laws of exponent 1 and 2);
  ``sin(z)`` or ``tan(z)`` of a force in newtons would be an accident of its units.
- :class:`WeakForm`: on a periodic record a linear filter ``H`` commutes with ``d/dt``, so
  ``H[z'] = H[theta(v, z)] xi`` holds exactly for clean data and no candidate column is
  differentiated; ``H`` is a raised-cosine low-pass from ``f_max / 4`` to ``f_max / 2``.
- :func:`screen`: the relevance vector machine (extended-BIC penalty) on those rows, with the
  rows' effective count ``N_eff = 2 N f_stop / f_s`` (the filtered rows are correlated).

Measured on the Bouc-Wen benchmark: the screen keeps the three true terms and six spurious ones
(its residual, 171 N/s, is above the propagated noise, 41 N/s: the band limit and the aliased
harmonics of ``|v|`` leave a systematic error the evidence over-rewards). It is a screen with full
recall, and the output-error selection that follows removes the rest.
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from .._regression.gram import GramStats
from .._regression.rvm import RVM
from .._symbolic.evaluator import Evaluator
from .._symbolic.library import Library, Term
from .periodic import Spectra, raised_cosine

__all__ = ["homogeneous_terms", "WeakForm", "screen", "evaluate"]


def _is_homogeneous(expr: sp.Expr, fractional: bool = False) -> bool:
    """A product of symbols, integer powers (positive rational ones if ``fractional``: a square root), absolute
    values and signs of symbols (no sums, no constants but 1)."""
    if expr == 1 or expr.is_Symbol:
        return True
    if isinstance(expr, (sp.Abs, sp.sign)):
        return expr.args[0].is_Symbol
    if expr.is_Pow:
        power = expr.exp.is_Rational if fractional else expr.exp.is_Integer
        return bool(power) and expr.exp > 0 and _is_homogeneous(expr.base, fractional)
    if expr.is_Mul:
        return all(_is_homogeneous(a, fractional) for a in expr.args)
    return False


def homogeneous_terms(terms, allowed: set[str], exclude=(), fractional: bool = False) -> list[Term]:
    """The terms of ``terms`` that are homogeneous in the variables and use only the ``allowed`` ones (see
    :func:`_is_homogeneous` for ``fractional``)."""
    out = []
    for term in terms:
        names = {s.name for s in term.sympy.free_symbols}
        if names <= allowed and term.name not in exclude and _is_homogeneous(term.sympy, fractional):
            out.append(term)
    return out


def evaluate(terms, variables, chunk_size: int = 4096, jit="auto"):
    """A function of a dict ``{variable name: samples}`` returning every term at every sample,
    shape ``(n_samples, n_terms)``, through the library's compiled :class:`~symsbl.Evaluator` (``chunk_size``
    and ``jit`` as its own)."""
    evaluator = Evaluator(Library(list(terms), list(variables)), chunk_size=chunk_size, jit=jit)

    def values_of(values: dict) -> np.ndarray:
        n = len(next(iter(values.values())))
        return evaluator.evaluate(
            np.column_stack([np.broadcast_to(np.asarray(values[v.name()], dtype=float), (n,)) for v in variables])
        )

    return values_of


class WeakForm:
    """Filtered rows of a law on a periodic record.

    Parameters
    ----------
    spectra : Spectra
    """

    def __init__(self, spectra: Spectra):
        self.spectra = spectra
        self.f_pass, self.f_stop = spectra.f_max / 4, spectra.f_max / 2
        self.H = raised_cosine(spectra.f, self.f_pass, self.f_stop)
        self.rows = np.flatnonzero(spectra.valid)
        n = self.rows.size
        self.n_eff = float(min(n, n * 2 * self.f_stop / spectra.fs))

    def filter(self, x: np.ndarray) -> np.ndarray:
        """``H`` applied to each column of ``x`` (periodic)."""
        X = np.fft.rfft(x, axis=0)
        H = self.H[:, None] if x.ndim == 2 else self.H
        return np.fft.irfft(X * H, self.spectra.N, axis=0)

    def derivative(self, x: np.ndarray) -> np.ndarray:
        """``H[x']`` of a periodic signal."""
        return np.fft.irfft(np.fft.rfft(x) * self.spectra.iw * self.H, self.spectra.N)

    def unexplained(self, columns_of, m: float, c: float, k: float, linear: int) -> float:
        """Split criterion: residual of the full law over the residual of the ``linear`` column alone."""
        z = self.spectra.force(m, c, k)
        lhs = self.derivative(z)[self.rows]
        A = self.filter(columns_of(z))[self.rows]
        A = A / np.maximum(np.linalg.norm(A, axis=0), 1e-300)

        def rss(B):
            coef, *_ = np.linalg.lstsq(B, lhs, rcond=None)
            return float(np.sum((lhs - B @ coef) ** 2))

        return rss(A) / max(rss(A[:, [linear]]), 1e-300)

    def stats(self, A: np.ndarray, target: np.ndarray) -> GramStats:
        """Gram statistics of the filtered rows the regressions use, weighted to their effective count ``n_eff``."""
        A, target = A[self.rows], target[self.rows]
        w = self.n_eff / A.shape[0]
        gram, dty = A.T @ A, A.T @ target[:, None]
        return GramStats(
            w * gram, w * dty, w * np.array([target @ target]), w * np.array([target.sum()]), int(round(self.n_eff))
        )


def screen(stats: GramStats, free=(), template: RVM | None = None) -> RVM:
    """The relevance vector machine (extended-BIC penalty, or the ``template``'s options) on weak-form
    statistics."""
    params = template.get_params() if template is not None else {}
    return RVM(**dict(params, free=tuple(free))).fit_stats(stats, 0)
