"""CasADi plumbing shared by the evaluator, the simulator and the output-error refinement.

- operation tables: which CasADi operations make an expression non-smooth or discontinuous;
- symbol checks: scalar SX symbols with distinct names;
- :func:`jit_wrap`: compile a (mapped) Function into one C loop with gcc through CasADi's
  ``shell`` JIT when a compiler exists, with a fallback to CasADi's virtual machine, cached
  per process;
- :func:`interrupts_kept`: a Ctrl-C that a CasADi solver notices is raised, not turned into a solver failure;
- :func:`run_chunks`: call a Function of fixed chunk size over row-major numpy arrays through
  ``Function.buffer()``, padding the last partial chunk.

A ``(k, chunk)`` CasADi matrix is column-major, i.e. the same memory as a C-ordered
``(chunk, k)`` numpy array, so ``buffer()`` reads and writes numpy rows in place.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import io
import itertools
import os
import shutil
import subprocess
import sys
import tempfile
from collections import OrderedDict

import casadi as ca
import numpy as np

from ._errors import SymsblError, expected
from ._interrupt import sigint_recorded

__all__ = [
    "NONSMOOTH_OPS", "DISCONTINUOUS_OPS", "uses_ops", "scalar_symbols", "compiler", "jit_wrap", "jit_lookup",
    "interrupts_kept", "run_chunks",
]

#: CasADi operations whose value or slope jumps: an expression using any of them is not smooth.
NONSMOOTH_OPS = frozenset(
    getattr(ca, f"OP_{name}")
    for name in (
        "SIGN", "FABS", "FMIN", "FMAX", "IF_ELSE_ZERO", "FLOOR", "CEIL", "FMOD", "REMAINDER",
        "COPYSIGN", "LT", "LE", "EQ", "NE", "NOT", "AND", "OR",
    )
)

#: The subset whose value jumps (as opposed to a kink such as abs, min, max): adaptive solvers stall on these.
DISCONTINUOUS_OPS = frozenset(
    getattr(ca, f"OP_{name}")
    for name in ("SIGN", "IF_ELSE_ZERO", "FLOOR", "CEIL", "FMOD", "REMAINDER", "COPYSIGN", "LT", "LE", "EQ", "NE",
                 "NOT", "AND", "OR")
)

_JIT_FLAGS = ["-O3", "-march=native", "-w"]  # -w: generated code (empty copies) warns harmlessly
_JIT_CACHE: OrderedDict[tuple, ca.Function] = OrderedDict()
_JIT_CACHE_SIZE = 64
_JIT_SEEN: set = set()  # keys asked for without compiling (jit="auto" on short data)
_JIT_DIR: str | None = None
_COUNTER = itertools.count()


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
        raise error(expected(what, "a sequence of scalar casadi.SX symbols", type(symbols).__name__,
                             "create them with symsbl.symbols('x1 x2')", raw=True))
    out = tuple(symbols)
    for i, s in enumerate(out):
        if not isinstance(s, ca.SX) or not s.is_scalar() or not s.is_symbolic():
            raise error(expected(f"{what}[{i}]", "a scalar casadi.SX symbol", s,
                                 "create symbols with symsbl.symbols('x1 x2')"))
    names = [s.name() for s in out]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise error(expected(what, "distinct symbol names", names, f"rename the repeated {repeated}"))
    return out


def compiler() -> str | None:
    """The C compiler CasADi's JIT will call (gcc or cc on PATH), or None."""
    return shutil.which("gcc") or shutil.which("cc")


def _jit_dir() -> str:
    global _JIT_DIR
    if _JIT_DIR is None:
        _JIT_DIR = tempfile.mkdtemp(prefix="symsbl_jit_")
        atexit.register(shutil.rmtree, _JIT_DIR, True)
    return _JIT_DIR + "/"


def jit_lookup(key) -> ca.Function | None:
    """A compiled function cached under ``key`` by :func:`jit_wrap`, or None."""
    if key in _JIT_CACHE:
        _JIT_CACHE.move_to_end(key)
        return _JIT_CACHE[key]
    return None


def jit_wrap(fn: ca.Function, name: str, jit, error: type[SymsblError], *,
             only_cached: bool = False, key=None) -> tuple[ca.Function, bool]:
    """``fn`` compiled as one C function (an MX wrapper, JIT with gcc), or ``fn`` itself.

    Compiling a wrapper around a ``map`` or ``mapaccum`` produces one C loop, which removes
    CasADi's per-call overhead of the virtual machine (0.1-1 us a sample). Compiled functions are
    cached per process by their serialised graph.

    Parameters
    ----------
    fn : ca.Function
    name : str
    jit : {"auto", True, False}
        ``"auto"`` compiles when a compiler exists and falls back silently; ``True`` requires it.
    error : SymsblError subclass
        Raised when ``jit=True`` cannot be honoured.
    only_cached : bool
        Compile only if the same function was asked for before (compiling would not pay off for one
        short use, and does for a structure used again: fits over many records, seeds or windows).
    key : hashable, optional
        The cache key (default: a hash of ``fn``'s serialised graph and ``name``); a caller that
        knows a cheaper one (the small step the function was built from) passes it.

    Returns
    -------
    (ca.Function, bool)
        The function to call and whether it is compiled.
    """
    if jit is False:
        return fn, False
    if compiler() is None:
        if jit is True:
            raise error(expected("jit", "a C compiler (gcc or cc on PATH) for jit=True", "none found",
                                 "install gcc or pass jit='auto'", raw=True))
        return fn, False
    key = (hashlib.sha1(fn.serialize().encode()).hexdigest(), name) if key is None else key
    cached = jit_lookup(key)
    if cached is not None:
        return cached, True
    if only_cached and key not in _JIT_SEEN:  # compiled from the second request on: a structure used again
        _JIT_SEEN.add(key)
        return fn, False
    args = [ca.MX.sym(fn.name_in(i), fn.sparsity_in(i)) for i in range(fn.n_in())]
    wrapper = ca.Function(name, args, fn.call(args), fn.name_in(), fn.name_out())
    try:
        compiled = _compile(wrapper)
    except (RuntimeError, OSError, subprocess.CalledProcessError) as err:
        if jit is True:
            text = err.stderr.decode(errors="replace") if isinstance(err, subprocess.CalledProcessError) else str(err)
            reason = (text.strip().splitlines() or [str(err)])[-1][:200]
            raise error(expected("jit", "a successful compilation for jit=True", reason, "pass jit='auto'",
                                 raw=True)) from None
        return fn, False
    _JIT_CACHE[key] = compiled
    if len(_JIT_CACHE) > _JIT_CACHE_SIZE:
        _JIT_CACHE.popitem(last=False)
    return compiled, True


def _compile(fn: ca.Function) -> ca.Function:
    """``fn`` generated as C, compiled into a shared library by the C compiler and loaded back.

    The compiler runs as a Python subprocess, so Ctrl-C during a compilation interrupts the program.
    CasADi's own JIT starts it through ``system()``, which ignores SIGINT in the caller while the
    compiler runs: an interrupt sent to the program in that window was lost, and the run went on.
    """
    base = f"{fn.name()}_{next(_COUNTER)}"
    generator = ca.CodeGenerator(base + ".c", {"with_header": False})
    generator.add(fn)
    source = generator.generate(_jit_dir())
    library = os.path.join(_jit_dir(), base + ".so")
    subprocess.run([compiler(), *_JIT_FLAGS, "-shared", "-fPIC", source, "-o", library], check=True,
                   capture_output=True)
    return ca.external(fn.name(), library)


@contextlib.contextmanager
def interrupts_kept():
    """Raise ``KeyboardInterrupt`` at the end of the block if Ctrl-C was pressed inside it.

    CasADi's SUNDIALS callbacks poll Python for interrupts; one that arrives during a CVODES run is
    consumed there and comes back as a solver failure (``CV_RHSFUNC_FAIL``), which would read as a
    diverging model. The interrupt is raised again when the block ends, whatever the solver made of it
    (:func:`symsbl._interrupt.sigint_recorded`), and CasADi's report of it on standard error is dropped
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
            buf.set_arg(i, memoryview(a[start:start + chunk]))
        for j, o in enumerate(outputs):
            buf.set_res(j, memoryview(o[start:start + chunk]))
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
        buf.set_arg(i, memoryview(p))
    for j, s in enumerate(scratch):
        buf.set_res(j, memoryview(s))
    call()
    for o, s in zip(outputs, scratch):
        o[full:] = s[:rest]
