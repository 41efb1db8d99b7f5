"""Compiled evaluation of a whole library into a design matrix, chunk by chunk.

The library becomes one SX ``casadi.Function`` ``z (n_variables) -> d (n_terms)``. One
``map(chunk_size)`` of it is built once, compiled as a single C loop with gcc (CasADi's
``shell`` JIT) when a C compiler is available, else run on CasADi's SX virtual machine, and
called through ``Function.buffer()``, which reads and writes numpy memory directly: CasADi's column-major
``(n_variables, chunk)`` input and ``(n_terms, chunk)`` output are exactly the C-ordered
rows ``Z[a:b]`` and ``D[a:b]``, so full chunks need no copies at all. Memory beyond the
output stays O(chunk_size * n_terms) for any number of samples; ``map(n_samples)`` with a
large count is never built (it costs O(n_samples * n_terms) memory in CasADi 3.8).
"""

from __future__ import annotations

import functools
from collections.abc import Iterator

import casadi as ca
import numpy as np

from .._base.casadi import run_chunks
from .._base.checks import choice, integer
from .._base.errors import LibraryError, expected
from .._base.jit import jit_wrap
from .library import Library

__all__ = ["Evaluator", "PARALLEL"]

#: Parallelisation strategies of CasADi's ``map``, by name (``openmp`` is serial in the PyPI wheel).
PARALLEL = {"serial": ("serial", 1), "thread": ("thread", 2)}
_JIT_MODES = ("auto", True, False)


@functools.lru_cache(maxsize=32)
def _compile(library: Library, chunk_size: int, jit: bool | str, parallel: str) -> tuple[ca.Function, bool, int]:
    """The chunk Function, whether it is compiled and its chunk size; cached per equal library.

    With ``parallel="thread"`` each of the 2 workers evaluates half a chunk, so the chunk size
    is rounded up to a multiple of 2. Compiling the loop, rather than mapping a compiled
    per-sample function, removes CasADi's per-sample call overhead (about 0.1-0.2 us a sample,
    which dominates for small libraries).
    """
    f = library.function("dictionary")
    mode, workers = PARALLEL[parallel]
    n = -(-chunk_size // workers)
    inner, compiled = jit_wrap(f.map(n), "dictionary_chunk", jit, LibraryError)
    return (inner.map(workers, mode, workers) if workers > 1 else inner), compiled, n * workers


class Evaluator:
    """Evaluate every term of a library on many samples.

    Parameters
    ----------
    library : Library
    chunk_size : int, default 4096
        Samples per call of the chunk Function; bounds the working memory. Rounded up to
        an even number with ``parallel="thread"``.
    jit : {"auto", True, False}, default "auto"
        ``"auto"`` compiles with gcc when a compiler exists and silently falls back to the
        SX virtual machine; ``True`` requires compilation; ``False`` never compiles.
    parallel : {"serial", "thread"}, default "serial"
        CasADi ``map`` strategy; ``"thread"`` uses 2 worker threads.

    Attributes
    ----------
    library : Library
    n_terms : int
    is_compiled : bool
        Whether the JIT-compiled code is used.

    Notes
    -----
    Compiled Functions are cached per (equal library, chunk_size, jit, parallel), so a
    second Evaluator for the same library does not recompile.

    Examples
    --------
    One row per sample, one column per term, in the library's order:

    >>> import numpy as np
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> lib = symsbl.polynomial([x1, x2], 2)
    >>> lib.names
    ['1', 'x1', 'x2', 'x1**2', 'x1*x2', 'x2**2']
    >>> symsbl.Evaluator(lib, jit=False).evaluate(np.array([[1.0, 2.0], [3.0, -1.0]]))
    array([[ 1.,  1.,  2.,  1.,  2.,  4.],
           [ 1.,  3., -1.,  9., -3.,  1.]])
    """

    def __init__(self, library: Library, *, chunk_size: int = 4096, jit: bool | str = "auto", parallel: str = "serial"):
        if not isinstance(library, Library):
            raise LibraryError(expected("library", "a symsbl Library", type(library).__name__, raw=True))
        if len(library) == 0:
            raise LibraryError(expected("library", "at least one term", "an empty library", raw=True))
        chunk_size = integer("chunk_size", chunk_size, low=1, error=LibraryError)
        jit = choice("jit", jit, _JIT_MODES, error=LibraryError)
        parallel = choice("parallel", parallel, PARALLEL, error=LibraryError)
        self.library = library
        self.jit = jit
        self.parallel = parallel
        self._mapped, self.is_compiled, self.chunk_size = _compile(library, chunk_size, jit, parallel)
        self.n_terms = len(library)

    def __repr__(self) -> str:
        how = "compiled" if self.is_compiled else "SX virtual machine"
        return f"Evaluator({self.n_terms} terms, chunk_size={self.chunk_size}, {how}, {self.parallel})"

    def _check(self, Z) -> np.ndarray:
        names = self.library.variable_names
        try:
            Z = np.ascontiguousarray(Z, dtype=np.float64)
        except (TypeError, ValueError):
            raise LibraryError(
                expected("Z", f"a numeric array of shape (n_samples, {len(names)})", type(Z).__name__, raw=True)
            ) from None
        if Z.ndim != 2 or Z.shape[1] != len(names):
            fix = "pass one column per variable in that order"
            if Z.ndim == 1 and len(names) == 1:
                fix += " (reshape a single column with Z.reshape(-1, 1))"
            raise LibraryError(
                expected(
                    "Z", f"shape (n_samples, {len(names)}) with columns {names}", f"shape {Z.shape}", fix, raw=True
                )
            )
        return Z

    def evaluate(self, Z, out: np.ndarray | None = None) -> np.ndarray:
        """The design matrix of the library at the samples ``Z``.

        Parameters
        ----------
        Z : array_like, shape (n_samples, n_variables)
            Columns in ``library.variables`` order.
        out : ndarray, shape (n_samples, n_terms), optional
            C-contiguous float64 array to write into.

        Returns
        -------
        ndarray, shape (n_samples, n_terms)
            C-ordered float64; ``out`` if given.
        """
        Z = self._check(Z)
        shape = (Z.shape[0], self.n_terms)
        if out is None:
            out = np.empty(shape)
        elif (
            not isinstance(out, np.ndarray)
            or out.shape != shape
            or out.dtype != np.float64
            or not out.flags.c_contiguous
            or not out.flags.writeable
        ):
            got = f"{out.dtype} array of shape {out.shape}" if isinstance(out, np.ndarray) else type(out).__name__
            raise LibraryError(
                expected(
                    "out",
                    f"a writeable C-contiguous float64 array of shape {shape}",
                    got,
                    "allocate it with np.empty((n_samples, n_terms))",
                    raw=True,
                )
            )
        if Z.shape[0]:
            run_chunks(self._mapped, self.chunk_size, [Z], [out])
        return out

    def iter_chunks(self, Z) -> Iterator[tuple[slice, np.ndarray]]:
        """Evaluate chunk by chunk without holding the whole design matrix.

        Parameters
        ----------
        Z : array_like, shape (n_samples, n_variables)

        Yields
        ------
        rows : slice
            The rows of ``Z`` of this chunk.
        D : ndarray, shape (rows.stop - rows.start, n_terms)
            A fresh array per chunk.
        """
        Z = self._check(Z)
        c = self.chunk_size
        for start in range(0, Z.shape[0], c):
            rows = slice(start, min(start + c, Z.shape[0]))
            block = np.empty((rows.stop - rows.start, self.n_terms))
            run_chunks(self._mapped, c, [Z[rows]], [block])
            yield rows, block
