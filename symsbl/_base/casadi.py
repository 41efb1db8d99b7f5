"""CasADi plumbing shared by the evaluator, the simulator and the output-error refinement
(compilation to C is :mod:`symsbl._base.jit`).

- operation tables: which CasADi operations make an expression non-smooth or discontinuous;
- symbol checks: scalar SX symbols with distinct names;
- :func:`interrupts_kept`: a Ctrl-C that a CasADi solver notices is raised, not turned into a solver failure;
- :func:`run_chunks`: call a Function of fixed chunk size over row-major numpy arrays through
  ``Function.buffer()``, padding the last partial chunk.

A ``(k, chunk)`` CasADi matrix is column-major, i.e. the same memory as a C-ordered
``(chunk, k)`` numpy array, so ``buffer()`` reads and writes numpy rows in place.
"""

from __future__ import annotations

import contextlib
import io
import sys

import casadi as ca
import numpy as np

from .errors import SymsblError, expected
from .interrupt import sigint_recorded

__all__ = [
    "NONSMOOTH_OPS",
    "DISCONTINUOUS_OPS",
    "uses_ops",
    "scalar_symbols",
    "interrupts_kept",
    "run_chunks",
]

#: CasADi operations whose value or slope jumps: an expression using any of them is not smooth.
NONSMOOTH_OPS = frozenset(
    getattr(ca, f"OP_{name}")
    for name in (
        "SIGN",
        "FABS",
        "FMIN",
        "FMAX",
        "IF_ELSE_ZERO",
        "FLOOR",
        "CEIL",
        "FMOD",
        "REMAINDER",
        "COPYSIGN",
        "LT",
        "LE",
        "EQ",
        "NE",
        "NOT",
        "AND",
        "OR",
    )
)

#: The subset whose value jumps (as opposed to a kink such as abs, min, max): adaptive solvers stall on these.
DISCONTINUOUS_OPS = frozenset(
    getattr(ca, f"OP_{name}")
    for name in (
        "SIGN",
        "IF_ELSE_ZERO",
        "FLOOR",
        "CEIL",
        "FMOD",
        "REMAINDER",
        "COPYSIGN",
        "LT",
        "LE",
        "EQ",
        "NE",
        "NOT",
        "AND",
        "OR",
    )
)


def uses_ops(exprs, ops=NONSMOOTH_OPS) -> bool:
    """True if any instruction of the SX expressions ``exprs`` is one of ``ops``."""
    exprs = list(exprs)
    if not exprs:
        return False
    body = ca.vertcat(*exprs)
    f = ca.Function("ops_check", ca.symvar(body), [body])
    return any(f.instruction_id(k) in ops for k in range(f.n_instructions()))


def scalar_symbols(symbols, what: str, error: type[SymsblError]) -> tuple[ca.SX, ...]:
    """``symbols`` as a tuple of scalar SX symbols with distinct names, or ``error``."""
    if isinstance(symbols, ca.SX):
        symbols = [symbols[i] for i in range(symbols.numel())]
    if isinstance(symbols, str) or not hasattr(symbols, "__iter__"):
        raise error(
            expected(
                what,
                "a sequence of scalar casadi.SX symbols",
                type(symbols).__name__,
                "create them with symsbl.symbols('x1 x2')",
                raw=True,
            )
        )
    out = tuple(symbols)
    for i, s in enumerate(out):
        if not isinstance(s, ca.SX) or not s.is_scalar() or not s.is_symbolic():
            raise error(
                expected(f"{what}[{i}]", "a scalar casadi.SX symbol", s, "create symbols with symsbl.symbols('x1 x2')")
            )
    names = [s.name() for s in out]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise error(expected(what, "distinct symbol names", names, f"rename the repeated {repeated}"))
    return out


@contextlib.contextmanager
def interrupts_kept():
    """Raise ``KeyboardInterrupt`` at the end of the block if Ctrl-C was pressed inside it.

    CasADi's SUNDIALS callbacks poll Python for interrupts; one that arrives during a CVODES run is
    consumed there and comes back as a solver failure (``CV_RHSFUNC_FAIL``), which would read as a
    diverging model. The interrupt is raised again when the block ends, whatever the solver made of it
    (:func:`symsbl._base.interrupt.sigint_recorded`), and CasADi's report of it on standard error is dropped
    (anything else written there is passed on at the end).
    """
    held = io.StringIO()  # CasADi reports the interrupt on sys.stderr ("rhs failed: KeyboardInterrupt")
    with sigint_recorded() as pressed:
        try:
            with contextlib.redirect_stderr(held):
                yield
        finally:
            if pressed():
                raise KeyboardInterrupt from None  # noqa: B012 - the interrupt comes first, whatever was raised
            if held.getvalue():
                sys.stderr.write(held.getvalue())


def run_chunks(fn: ca.Function, chunk: int, inputs: list[np.ndarray], outputs: list[np.ndarray]) -> None:
    """Call ``fn`` (inputs ``(k_i, chunk)``, outputs ``(m_j, chunk)``) over ``(n, k_i)`` arrays.

    ``inputs`` are C-contiguous float64 ``(n, k_i)`` arrays, ``outputs`` preallocated C-contiguous
    ``(n, m_j)`` arrays written in place. The last ``n % chunk`` rows go through padded scratch
    arrays (the padding repeats the last row, so it stays in the function's domain).
    """
    n = inputs[0].shape[0]
    buf, call = fn.buffer()
    full = n - n % chunk
    for start in range(0, full, chunk):
        for i, a in enumerate(inputs):
            buf.set_arg(i, memoryview(a[start : start + chunk]))  # type: ignore[call-arg, arg-type]
        for j, o in enumerate(outputs):
            buf.set_res(j, memoryview(o[start : start + chunk]))  # type: ignore[call-arg, arg-type]
        call()
    if full == n:
        return
    rest = n - full
    pads = []
    for a in inputs:
        pad = np.empty((chunk, a.shape[1]))
        pad[:rest] = a[full:]
        pad[rest:] = a[-1]
        pads.append(pad)
    scratch = [np.empty((chunk, o.shape[1])) for o in outputs]
    for i, p in enumerate(pads):
        buf.set_arg(i, memoryview(p))  # type: ignore[call-arg, arg-type]
    for j, s in enumerate(scratch):
        buf.set_res(j, memoryview(s))  # type: ignore[call-arg, arg-type]
    call()
    for o, s in zip(outputs, scratch):
        o[full:] = s[:rest]
