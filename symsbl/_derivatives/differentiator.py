"""The contract of a derivative strategy: how sampled states become regression rows, and which samples
each row reads (its stencil), so that a long record cut into blocks gives the rows of the whole."""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .._base.errors import DataError, expected

__all__ = ["Stencil", "Differentiator", "check_samples"]


def check_samples(t: np.ndarray, X: np.ndarray, min_samples: int) -> tuple[np.ndarray, float]:
    """``X`` as ``(n_samples, n_states)`` floats and the sample interval; refuse fewer than ``min_samples``."""
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or X.ndim != 2 or len(t) != len(X):
        raise DataError(
            expected(
                "t, X",
                "shapes (n_samples,) and (n_samples, n_states)",
                f"t.shape={t.shape}, X.shape={X.shape}",
                raw=True,
            )
        )
    if len(t) < min_samples:
        raise DataError(
            expected(
                "X",
                f"at least {min_samples} samples for this differentiator",
                f"{len(t)}",
                "use a longer record or a shorter window",
                raw=True,
            )
        )
    return X, float(t[1] - t[0])


@dataclass(frozen=True)
class Stencil:
    """Which samples a differentiator's rows need: what a block of a longer record can produce.

    Attributes
    ----------
    stride : int
        Sample intervals between the starts of consecutive rows for window strategies (windows
        aligned with the start of the record); 0 for pointwise strategies.
    left, right : int
        Pointwise strategies: samples a row reads either side of its own sample. Window
        strategies: ``left`` is the number of earlier rows a row is combined with (the
        whitening of overlapping windows; 0 when rows are independent), ``right`` is 0.
    min_samples : int
        Fewest samples that give a row.
    span : int
        Window strategies: sample intervals each window covers (0: ``stride``, windows that
        only share their end samples; a multiple of ``stride`` when windows overlap).

    Examples
    --------
    The weak form's windows of 10 sample intervals: a block of 35 samples gives 3 rows, and the
    next block starts from sample 30, the end of the last complete window:

    >>> import symsbl
    >>> stencil = symsbl.WeakForm(window=10).stencil
    >>> stencil.rows(35, first=True, last=False), stencil.carry_from(3), stencil.sample_span(0, 3)
    ((0, 3), 30, (0, 31))
    """

    stride: int
    left: int
    right: int
    min_samples: int
    span: int = 0

    @property
    def window(self) -> int:
        """Sample intervals one window covers (window strategies)."""
        return self.span or self.stride

    @property
    def min_block(self) -> int:
        """Fewest samples a block inside a record needs: its earlier rows and one row of its own."""
        return self.left * self.stride + self.window + 1 if self.stride else self.min_samples

    def rows(self, n: int, first: bool, last: bool) -> tuple[int, int]:
        """Rows ``[r0, r1)`` a block of ``n`` samples produces (``first``/``last``: at the record's ends).

        A block that does not start the record begins with the ``left`` rows its first row is
        combined with; they were produced by the block before.
        """
        if self.stride:
            windows = (n - 1 - self.window) // self.stride + 1 if n > self.window else 0
            return (0 if first else self.left), windows
        return (0 if first else self.left), (n if last else n - self.right)

    def carry_from(self, row_stop: int) -> int:
        """First sample the next block must start from when this one stopped at ``row_stop``."""
        return (row_stop - self.left) * self.stride if self.stride else row_stop - self.left

    def sample_span(self, r0: int, r1: int) -> tuple[int, int]:
        """Samples ``[s0, s1)`` whose dictionary rows reduce to rows ``[r0, r1)`` (window strategies:
        with the ``left`` earlier rows they are combined with, from the record's start at most)."""
        if self.stride:
            return max(r0 - self.left, 0) * self.stride, (r1 - 1) * self.stride + self.window + 1
        return r0, r1


class Differentiator(abc.ABC):
    """How sampled states become regression rows: targets from the states, rows of the dictionary.

    Contract (every strategy; :func:`symsbl.identify` and the streaming and Dask paths rely on
    nothing else):

    - ``targets(t, X)`` returns the derivative estimate for each row, ``(n_rows, n_states)``;
    - ``reduce(D)`` turns per-sample dictionary rows ``(n_samples, n_terms)`` into the rows that
      pair with those targets (identity for pointwise strategies, window integrals for the weak form);
      given the samples of ``sample_span(r0, r1)``, its last ``r1 - r0`` rows are rows ``r0:r1``;
    - ``n_rows(n)`` and ``sample_span(r0, r1)`` say how rows map to samples;
    - ``stencil`` declares the samples each row reads, so a long record can be cut into blocks
      whose rows equal those of the whole record;
    - ``resolve(t, X, n_terms)`` fixes data-dependent settings (the weak form's window) and
      returns a strategy with none left open; strategies without such settings return themselves.

    Examples
    --------
    A user's strategy: a fourth-order central difference, which reads two samples either side:

    >>> import numpy as np
    >>> import symsbl
    >>> class FourthOrder(symsbl.Differentiator):
    ...     stencil = symsbl.Stencil(stride=0, left=2, right=2, min_samples=5)
    ...     def targets(self, t, X):
    ...         X = np.asarray(X, dtype=float).reshape(len(t), -1)
    ...         h = t[1] - t[0]
    ...         d = np.gradient(X, h, axis=0, edge_order=2)
    ...         d[2:-2] = (X[:-4] - 8 * X[1:-3] + 8 * X[3:-1] - X[4:]) / (12 * h)
    ...         return d
    ...     def reduce(self, D):
    ...         return np.asarray(D, dtype=float)
    ...     def n_rows(self, n_samples):
    ...         return n_samples
    >>> t = np.linspace(0.0, 1.0, 201)
    >>> dx = FourthOrder().targets(t, np.sin(t)[:, None])
    >>> bool(np.max(np.abs(dx[2:-2, 0] - np.cos(t[2:-2]))) < 1e-9)
    True
    """

    name: ClassVar[str] = ""

    @abc.abstractmethod
    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Derivative estimate per row, shape ``(n_rows, n_states)``."""

    @abc.abstractmethod
    def reduce(self, D: np.ndarray) -> np.ndarray:
        """Dictionary rows paired with the targets, shape ``(n_rows, n_cols)``."""

    @abc.abstractmethod
    def n_rows(self, n_samples: int) -> int:
        """Number of regression rows produced from ``n_samples`` samples."""

    @property
    @abc.abstractmethod
    def stencil(self) -> Stencil:
        """The samples each row reads (see :class:`Stencil`)."""

    def sample_span(self, row_start: int, row_stop: int) -> tuple[int, int]:
        """Samples ``[start, stop)`` whose ``reduce`` gives rows ``[row_start, row_stop)``."""
        return self.stencil.sample_span(row_start, row_stop)

    def resolve(self, t: np.ndarray, X: np.ndarray, n_terms: int = 0) -> Differentiator:
        """This strategy with its data-dependent settings fixed; by default itself."""
        return self
