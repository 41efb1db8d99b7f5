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
import shutil
import tempfile
from collections.abc import Iterator

import casadi as ca
import numpy as np

from symsbl.errors import LibraryError
from symsbl.library import Library

__all__ = ["Evaluator"]

#: Parallelisation strategies of CasADi's ``map``, by name (``openmp`` is serial in the PyPI wheel).
PARALLEL = {"serial": ("serial", 1), "thread": ("thread", 2)}
_JIT_MODES = ("auto", True, False)
_JIT_FLAGS = ["-O3", "-march=native"]


def _compiler() -> str | None:
    return shutil.which("gcc") or shutil.which("cc")


def _jit_loop(f: ca.Function, n: int) -> ca.Function:
    """Compile ``n`` evaluations of ``f`` as one C loop (gcc, private directory removed once loaded).

    Compiling the loop, rather than mapping a compiled ``f``, removes CasADi's per-sample
    call overhead (about 0.1-0.2 us a sample, which dominates for small libraries).
    """
    z = ca.MX.sym("z", f.size1_in(0), n)
    with tempfile.TemporaryDirectory(prefix="symsbl_jit_") as directory:
        options = {
            "jit": True,
            "compiler": "shell",
            "jit_cleanup": False,
            "jit_options": {"directory": directory + "/", "flags": _JIT_FLAGS, "compiler": _compiler(), "cleanup": False},
        }
        return ca.Function(f"{f.name()}_chunk", [z], [f.map(n)(z)], ["z"], ["d"], options)


@functools.lru_cache(maxsize=32)
def _compile(library: Library, chunk_size: int, jit: bool | str, parallel: str) -> tuple[ca.Function, bool, int]:
    """The chunk Function, whether it is compiled and its chunk size; cached per equal library.

    With ``parallel="thread"`` each of the 2 workers evaluates half a chunk, so the chunk size
    is rounded up to a multiple of 2.
    """
    f = library.function("dictionary")
    mode, workers = PARALLEL[parallel]
    n = -(-chunk_size // workers)
    inner = None
    if jit is not False and _compiler() is not None:
        try:
            inner = _jit_loop(f, n)
        except RuntimeError as err:
            if jit is True:
                raise LibraryError(f"jit: compiling the library failed ({err}); pass jit='auto' or jit=False") from err
    elif jit is True:
        raise LibraryError("jit: jit=True needs a C compiler (gcc or cc on PATH); install one or pass jit='auto'")
    compiled = inner is not None
    if inner is None:
        inner = f.map(n)
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
            raise LibraryError(f"library: expected a symsbl Library, received {type(library).__name__}")
        if len(library) == 0:
            raise LibraryError("library: expected at least one term, received an empty library")
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
            raise LibraryError(f"chunk_size: expected a positive integer, received {chunk_size!r}")
        if not any(jit is m if isinstance(m, bool) else jit == m for m in _JIT_MODES):
            raise LibraryError(f"jit: expected one of {list(_JIT_MODES)}, received {jit!r}")
        if parallel not in PARALLEL:
            raise LibraryError(f"parallel: unknown strategy {parallel!r}; valid names: {sorted(PARALLEL)}")
        self.library = library
        self.jit = jit
        self.parallel = parallel
        self._mapped, self.is_compiled, self.chunk_size = _compile(library, int(chunk_size), jit, parallel)
        self.n_terms = len(library)

    def __repr__(self) -> str:
        how = "compiled" if self.is_compiled else "SX virtual machine"
        return f"Evaluator({self.n_terms} terms, chunk_size={self.chunk_size}, {how}, {self.parallel})"

    def _check(self, Z) -> np.ndarray:
        names = self.library.variable_names
        try:
            Z = np.ascontiguousarray(Z, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise LibraryError(f"Z: expected a numeric array of shape (n_samples, {len(names)}), {err}") from None
        if Z.ndim != 2 or Z.shape[1] != len(names):
            raise LibraryError(
                f"Z: expected shape (n_samples, {len(names)}) with columns {names}, "
                f"received shape {Z.shape}; pass one column per variable in that order"
                + (" (reshape a single column with Z.reshape(-1, 1))" if Z.ndim == 1 and len(names) == 1 else "")
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
            raise LibraryError(
                f"out: expected a writeable C-contiguous float64 array of shape {shape}, received "
                + (f"{out.dtype} array of shape {out.shape}" if isinstance(out, np.ndarray) else type(out).__name__)
                + "; allocate it with np.empty((n_samples, n_terms))"
            )
        buffer, call = self._mapped.buffer()
        n, c = Z.shape[0], self.chunk_size
        full = n - n % c
        for start in range(0, full, c):
            buffer.set_arg(0, memoryview(Z[start : start + c]))
            buffer.set_res(0, memoryview(out[start : start + c]))
            call()
        if full < n:
            out[full:] = self._partial(Z[full:], buffer, call)
        return out

    def _partial(self, Zr: np.ndarray, buffer, call) -> np.ndarray:
        """Evaluate fewer than chunk_size rows through padded scratch arrays."""
        zin = np.empty((self.chunk_size, Zr.shape[1]))
        zin[: len(Zr)] = Zr
        zin[len(Zr) :] = Zr[-1]
        res = np.empty((self.chunk_size, self.n_terms))
        buffer.set_arg(0, memoryview(zin))
        buffer.set_res(0, memoryview(res))
        call()
        return res[: len(Zr)]

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
        buffer, call = self._mapped.buffer()
        c = self.chunk_size
        for start in range(0, Z.shape[0], c):
            rows = slice(start, min(start + c, Z.shape[0]))
            if rows.stop - rows.start < c:
                yield rows, self._partial(Z[rows], buffer, call).copy()
                continue
            block = np.empty((c, self.n_terms))
            buffer.set_arg(0, memoryview(Z[rows]))
            buffer.set_res(0, memoryview(block))
            call()
            yield rows, block
