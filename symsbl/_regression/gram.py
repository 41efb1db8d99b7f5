"""Sufficient statistics of a regression: ``D^T D``, ``D^T Y``, ``Y^T Y``, ``sum Y`` and ``N``.

Everything the relevance vector machine needs from a dictionary ``D`` (n_samples, n_terms) and
its targets ``Y`` fits in :class:`GramStats`, which adds across chunks, records and machines, so a
record of 10^7 samples is reduced chunk by chunk and one Gram matrix serves every target.

``D^T D`` is built by symmetric rank-k updates (BLAS ``dsyrk``, half the flops of a general
product) block by block, with ``D^T Y`` taken from each block in the same pass.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from .._base.checks import integer, number
from .._base.errors import DataError, expected

__all__ = ["GramStats", "check_target"]


def _as_matrix(value, name, *, ndim_ok=(2,), check_finite=True):
    arr = np.asarray(value, dtype=float)
    if arr.ndim not in ndim_ok:
        raise DataError(
            expected(
                name,
                f"a {' or '.join(f'{d}-D' for d in ndim_ok)} array",
                f"shape {arr.shape}",
                f"reshape it (e.g. {name}.reshape(-1, 1) for one column)",
                raw=True,
            )
        )
    if check_finite:
        _require_finite(arr, name)
    return arr


def _require_finite(arr, name):
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise DataError(
            expected(
                name,
                "finite values",
                f"a non-finite value at index {tuple(int(i) for i in bad)}",
                "remove or impute NaN/inf rows first",
                raw=True,
            )
        )


def _check_pair(D, Y, names=("D", "Y")):
    # Finiteness is checked on the statistics (a NaN or inf anywhere reaches the diagonal of
    # D^T D or Y^T Y), so valid data is never scanned twice.
    D = _as_matrix(D, names[0], check_finite=False)
    Y = _as_matrix(Y, names[1], ndim_ok=(1, 2), check_finite=False)
    Y = Y.reshape(len(Y), -1)
    if len(D) != len(Y):
        raise DataError(expected(names[1], f"as many rows as {names[0]} ({len(D)})", f"{len(Y)} rows", raw=True))
    return D, Y


def _tsqr(r_old, block):
    """Upper-triangular R of ``[r_old; block]`` (square, zero-padded)."""
    stacked = block if r_old is None else np.vstack([r_old, block])
    r = np.linalg.qr(stacked, mode="r")
    width = stacked.shape[1]
    if r.shape[0] < width:
        r = np.vstack([r, np.zeros((width - r.shape[0], width))])
    return r


@dataclass(frozen=True)
class GramStats:
    """Sufficient statistics of a dictionary and its targets.

    Parameters
    ----------
    gram : ndarray, shape (n_terms, n_terms)
        ``D^T D``.
    dty : ndarray, shape (n_terms, n_targets)
        ``D^T Y``.
    yty : ndarray, shape (n_targets,)
        ``sum_n Y[n, k]^2``.
    y_sum : ndarray, shape (n_targets,)
        ``sum_n Y[n, k]`` (for the target variance).
    n_samples : float
        Number of rows (an effective, possibly non-integer count after :meth:`scaled`).
    r_factor : ndarray, shape (n_terms + n_targets, n_terms + n_targets), or None
        Upper-triangular R with ``[D | Y] = Q R``, carried when built with ``qr=True`` so that
        residuals avoid the cancellation of the Gram identity.

    Examples
    --------
    Statistics add up across chunks (or machines) to those of the whole record:

    >>> import numpy as np
    >>> import symsbl
    >>> rng = np.random.default_rng(0)
    >>> D = rng.standard_normal((1000, 4))
    >>> Y = D @ np.array([[1.0], [0.0], [-2.0], [0.0]])
    >>> whole = symsbl.GramStats.from_arrays(D, Y)
    >>> parts = symsbl.GramStats.from_arrays(D[:600], Y[:600]) + symsbl.GramStats.from_arrays(D[600:], Y[600:])
    >>> bool(np.allclose(whole.gram, parts.gram)), parts.n_samples, parts.n_terms, parts.n_targets
    (True, 1000, 4, 1)
    """

    gram: np.ndarray
    dty: np.ndarray
    yty: np.ndarray
    y_sum: np.ndarray
    n_samples: float
    r_factor: np.ndarray | None = None

    @property
    def n_terms(self) -> int:
        return self.gram.shape[0]

    @property
    def n_targets(self) -> int:
        return self.dty.shape[1]

    @classmethod
    def from_arrays(cls, D, Y, *, qr=False, chunk_size=8192, _names=("D", "Y")) -> GramStats:
        """Statistics of a dictionary ``D`` (n_samples, n_terms) and targets ``Y`` (n_samples,) or
        (n_samples, n_targets). ``qr=True`` also accumulates the factor R (chunks of ``chunk_size``
        rows)."""
        D, Y = _check_pair(D, Y, _names)
        (gram, dty), yty = _products(D, Y), np.einsum("nk,nk->k", Y, Y)
        _check_squares(D, Y, np.diag(gram), yty, _names)
        r_factor = None
        if qr:
            for start in range(0, len(D), chunk_size):
                stop = start + chunk_size
                r_factor = _tsqr(r_factor, np.hstack([D[start:stop], Y[start:stop]]))
        return cls(gram, dty, yty, Y.sum(axis=0), len(D), r_factor)

    @classmethod
    def from_chunks(cls, chunks: Iterable, *, qr=False) -> GramStats:
        """Accumulate over an iterable of ``(D_chunk, Y_chunk)`` pairs without holding D.

        Memory is O(n_terms^2) and cost O(N n_terms^2); the result equals :meth:`from_arrays`
        on the stacked data up to rounding."""
        total = None
        for D, Y in chunks:
            part = cls.from_arrays(D, Y, qr=qr, chunk_size=max(len(D), 1))
            total = part if total is None else total + part
        if total is None:
            raise DataError(expected("chunks", "at least one (D_chunk, Y_chunk) pair", "none", raw=True))
        return total

    def __add__(self, other: GramStats) -> GramStats:
        if not isinstance(other, GramStats):
            return NotImplemented
        if self.gram.shape != other.gram.shape or self.dty.shape != other.dty.shape:
            raise DataError(
                expected("other", f"GramStats of {self.dty.shape} (n_terms, n_targets)", f"{other.dty.shape}", raw=True)
            )
        r_factor = None
        if self.r_factor is not None and other.r_factor is not None:
            r_factor = _tsqr(self.r_factor, other.r_factor)
        return GramStats(
            self.gram + other.gram,
            self.dty + other.dty,
            self.yty + other.yty,
            self.y_sum + other.y_sum,
            self.n_samples + other.n_samples,
            r_factor,
        )

    def scaled(self, factor: float) -> GramStats:
        """Statistics of ``factor`` times as many samples (e.g. ``n_eff / n`` for correlated noise)."""
        factor = number("factor", factor, low=0.0, strict=True)
        r_factor = None if self.r_factor is None else np.sqrt(factor) * self.r_factor
        return GramStats(
            factor * self.gram,
            factor * self.dty,
            factor * self.yty,
            factor * self.y_sum,
            factor * self.n_samples,
            r_factor,
        )

    def target(self, k: int) -> GramStats:
        """Statistics of target ``k`` alone."""
        k = check_target(k, self.n_targets)
        r_factor = None
        if self.r_factor is not None:
            keep = list(range(self.n_terms)) + [self.n_terms + k]
            r_factor = self.r_factor[:, keep]
        return GramStats(self.gram, self.dty[:, [k]], self.yty[[k]], self.y_sum[[k]], self.n_samples, r_factor)


def _check_squares(D, Y, d2, yty, names):
    """Refuse non-finite data, found through the sums of squares (so valid data is scanned once)."""
    if not np.all(np.isfinite(d2)):
        _require_finite(D, names[0])
        raise DataError(
            expected(
                names[0],
                "values whose squares are finite",
                "values too large to square",
                "rescale its columns",
                raw=True,
            )
        )
    if not np.all(np.isfinite(yty)):
        _require_finite(Y, names[1])
        raise DataError(
            expected(names[1], "values whose squares are finite", "values too large to square", "rescale it", raw=True)
        )


def _products(D, Y):
    """``D^T D`` and ``D^T Y`` in one pass over ``D``, block by block.

    ``block.T @ block`` is a symmetric rank-k update: numpy hands a matrix times its own
    transpose to BLAS ``dsyrk`` (half the flops of a general product) and returns it exactly
    symmetric. Taking ``D^T Y`` from the same block while it is in cache saves the second pass
    over ``D`` that ``D.T @ Y`` would cost. Blocks of about 1 MiB keep one BLAS thread fast
    and still let several share a block.
    """
    n, M = D.shape
    step = max(256, _BLOCK_BYTES // (8 * max(M, 1)))
    # A block must reach BLAS without a copy of each operand for numpy to see A^T A (a strided
    # view of a C- or Fortran-ordered array does; anything else is copied once, block by block).
    direct = D.flags.c_contiguous or D.flags.f_contiguous
    if n <= step or D.size == 0:
        D = D if direct else np.ascontiguousarray(D)
        return D.T @ D, D.T @ Y
    gram, dty = np.zeros((M, M)), np.zeros((M, Y.shape[1]))
    part_g, part_y = np.empty((M, M)), np.empty((M, Y.shape[1]))
    for start in range(0, n, step):
        block = D[start : start + step] if direct else np.ascontiguousarray(D[start : start + step])
        np.matmul(block.T, block, out=part_g)
        np.matmul(block.T, Y[start : start + step], out=part_y)
        gram += part_g
        dty += part_y
    return gram, dty


#: Bytes of the design per block in :func:`_products`.
_BLOCK_BYTES = 1 << 20


def check_target(k, n_targets):
    """``k`` as a target index in ``[0, n_targets)``."""
    return integer("target", k, low=0, high=n_targets - 1)
