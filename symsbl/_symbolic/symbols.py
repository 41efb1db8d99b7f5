"""Exact conversion between CasADi SX expressions and sympy expressions.

CasADi -> sympy walks the instruction list of an SX ``Function`` (linear in the size of
the expression graph; shared subexpressions are converted once). sympy -> CasADi walks the
sympy expression tree. ``sympy.lambdify`` is not used for the latter because its printer
turns ``sign`` into a Python ``if`` that cannot be evaluated on symbolic CasADi values.

Integer-valued constants become sympy ``Integer`` objects and integer powers stay integer
(``x1**3``, never ``x1**3.0``), so that names printed from the sympy form are stable.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from fractions import Fraction
from functools import reduce

import casadi as ca
import sympy as sp

from .._base.casadi import NONSMOOTH_OPS, uses_ops
from .._base.errors import LibraryError, expected

__all__ = ["symbols", "casadi_to_sympy", "sympy_to_casadi", "is_smooth"]

_OP_NAMES = {getattr(ca, n): n for n in dir(ca) if n.startswith("OP_")}

# Unary CasADi operations and their sympy counterparts.
_UNARY = {
    ca.OP_NEG: lambda a: -a,
    ca.OP_SQ: lambda a: a**2,
    ca.OP_TWICE: lambda a: 2 * a,
    ca.OP_SQRT: sp.sqrt,
    ca.OP_INV: lambda a: 1 / a,
    ca.OP_EXP: sp.exp,
    ca.OP_LOG: sp.log,
    ca.OP_SIN: sp.sin,
    ca.OP_COS: sp.cos,
    ca.OP_TAN: sp.tan,
    ca.OP_ASIN: sp.asin,
    ca.OP_ACOS: sp.acos,
    ca.OP_ATAN: sp.atan,
    ca.OP_SINH: sp.sinh,
    ca.OP_COSH: sp.cosh,
    ca.OP_TANH: sp.tanh,
    ca.OP_ASINH: sp.asinh,
    ca.OP_ACOSH: sp.acosh,
    ca.OP_ATANH: sp.atanh,
    ca.OP_SIGN: sp.sign,
    ca.OP_FABS: sp.Abs,
    ca.OP_FLOOR: sp.floor,
    ca.OP_CEIL: sp.ceiling,
    ca.OP_ERF: sp.erf,
    ca.OP_ERFINV: sp.erfinv,
    ca.OP_LOG1P: lambda a: sp.log(1 + a),
    ca.OP_EXPM1: lambda a: sp.exp(a) - 1,
    ca.OP_ASSIGN: lambda a: a,
}

# Binary CasADi operations whose operands are numbers.
_BINARY = {
    ca.OP_ADD: lambda a, b: a + b,
    ca.OP_SUB: lambda a, b: a - b,
    ca.OP_MUL: lambda a, b: a * b,
    ca.OP_DIV: lambda a, b: a / b,
    ca.OP_POW: lambda a, b: a ** _exponent(b),
    ca.OP_CONSTPOW: lambda a, b: a ** _exponent(b),
    ca.OP_FMIN: sp.Min,
    ca.OP_FMAX: sp.Max,
    ca.OP_ATAN2: sp.atan2,
    ca.OP_COPYSIGN: lambda a, b: sp.Abs(a) * sp.sign(b),
    ca.OP_HYPOT: lambda a, b: sp.sqrt(a**2 + b**2),
    ca.OP_LT: sp.StrictLessThan,
    ca.OP_LE: sp.LessThan,
    ca.OP_EQ: sp.Eq,
    ca.OP_NE: sp.Ne,
}

_LOGICAL = {
    ca.OP_AND: sp.And,
    ca.OP_OR: sp.Or,
}


def symbols(names: str | Sequence[str]) -> tuple[ca.SX, ...]:
    """Create scalar CasADi SX symbols.

    Parameters
    ----------
    names : str or sequence of str
        Names separated by spaces and/or commas (``"x1 x2 F"`` or ``"x1,x2,F"``), or a
        sequence of names.

    Returns
    -------
    tuple of ca.SX
        One scalar symbol per name, in the given order.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> x1.name(), F.is_symbolic()
    ('x1', True)
    """
    if isinstance(names, str):
        parts = [p for p in re.split(r"[\s,]+", names) if p]
    else:
        parts = list(names)
    bad = [p for p in parts if not isinstance(p, str) or not re.fullmatch(r"[A-Za-z_]\w*", p)]
    if not parts or bad:
        raise LibraryError(
            f"names: expected identifiers such as 'x1 x2 F', received {names!r}"
            + (f" (invalid: {bad})" if bad else " (no names)")
            + "; use letters, digits and underscores, starting with a letter"
        )
    if len(set(parts)) != len(parts):
        raise LibraryError(f"names: expected distinct names, received {parts}; remove the repeated names")
    return tuple(ca.SX.sym(p) for p in parts)


def _number(value: float) -> sp.Expr:
    """Convert a CasADi constant: integers exactly, other values as binary-exact Floats."""
    if math.isnan(value):
        return sp.nan
    if math.isinf(value):
        return sp.oo if value > 0 else -sp.oo
    if value.is_integer():
        return sp.Integer(int(value))
    return sp.Float(value)


def _exponent(b: sp.Expr) -> sp.Expr:
    """An exponent that is a short exact fraction (1/3, 5/2) becomes a sympy Rational."""
    if isinstance(b, sp.Float):
        frac = Fraction(float(b)).limit_denominator(100)
        if float(frac) == float(b):
            return sp.Rational(frac.numerator, frac.denominator)
    return b


def _as_number(e):
    """Relational values used as numbers become 0/1 Piecewise expressions."""
    if _is_boolean(e):
        return sp.Piecewise((sp.Integer(1), e), (sp.Integer(0), True))
    return e


def _as_bool(e):
    """Numbers used as conditions mean 'nonzero', as in CasADi."""
    return e if _is_boolean(e) else sp.Ne(e, 0)


def _is_boolean(e) -> bool:
    # sympy Symbols are Booleans too; only relations and logic are not expressions.
    return isinstance(e, sp.logic.boolalg.Boolean) and not isinstance(e, sp.Expr)


def _flatten(expr) -> tuple[list[ca.SX], bool]:
    if isinstance(expr, (ca.SX, ca.DM, int, float)):
        sx = ca.densify(ca.SX(expr))
        return [sx[i] for i in range(sx.numel())], sx.is_scalar()
    if isinstance(expr, Sequence):
        return [_scalar(e, f"expr[{i}]") for i, e in enumerate(expr)], False
    raise LibraryError(f"expr: expected a casadi.SX expression or a list of them, received {type(expr).__name__}")


def _scalar(e, where: str) -> ca.SX:
    sx = ca.SX(e) if isinstance(e, (ca.SX, ca.DM, int, float)) else None
    if sx is None or not sx.is_scalar():
        raise LibraryError(
            f"{where}: expected a scalar casadi.SX expression, received "
            f"{type(e).__name__}{'' if sx is None else ' of shape ' + str(sx.shape)}"
        )
    return sx


def _function(exprs: Sequence[ca.SX]) -> tuple[ca.Function, list[ca.SX]]:
    free = ca.symvar(ca.vertcat(*exprs)) if exprs else []
    return ca.Function("convert", free, [ca.vertcat(*exprs)] if exprs else []), free


def casadi_to_sympy(expr, symbols: Mapping[str, sp.Symbol] | None = None):
    """Convert CasADi SX expressions to sympy, exactly.

    Parameters
    ----------
    expr : ca.SX or list of ca.SX
        A scalar expression, a vector/matrix expression (converted element by element,
        column-major) or a list of scalar expressions.
    symbols : mapping of str to sympy.Symbol, optional
        The sympy symbol to use for each SX symbol name. Names not given become real
        sympy symbols of the same name.

    Returns
    -------
    sympy.Expr or list of sympy.Expr
        A single expression for a scalar input, otherwise a list.

    Raises
    ------
    LibraryError
        If the expression uses a CasADi operation without a sympy counterpart.

    Examples
    --------
    >>> import casadi as ca
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> symsbl.casadi_to_sympy(x1 * ca.fabs(x2) + ca.sin(x1))
    x1*Abs(x2) + sin(x1)
    >>> symsbl.casadi_to_sympy([x1**2, ca.sign(x2)])
    [x1**2, sign(x2)]
    """
    items, scalar = _flatten(expr)
    symbols = dict(symbols or {})
    f, free = _function(items)
    inputs = []
    for s in free:
        name = s.name()
        inputs.append(symbols.get(name) or sp.Symbol(name, real=True))
    work: dict[int, sp.Expr] = {}
    out: list = [sp.Integer(0)] * len(items)
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        args = f.instruction_input(k)
        res = f.instruction_output(k)
        if op == ca.OP_INPUT:
            work[res[0]] = inputs[args[0]]
        elif op == ca.OP_OUTPUT:
            out[res[1]] = _as_number(work[args[0]])
        elif op == ca.OP_CONST:
            work[res[0]] = _number(f.instruction_constant(k))
        elif op in _UNARY:
            work[res[0]] = _UNARY[op](_as_number(work[args[0]]))
        elif op in _BINARY:
            work[res[0]] = _BINARY[op](_as_number(work[args[0]]), _as_number(work[args[1]]))
        elif op in _LOGICAL:
            work[res[0]] = _LOGICAL[op](_as_bool(work[args[0]]), _as_bool(work[args[1]]))
        elif op == ca.OP_NOT:
            work[res[0]] = sp.Not(_as_bool(work[args[0]]))
        elif op == ca.OP_IF_ELSE_ZERO:
            cond, value = _as_bool(work[args[0]]), _as_number(work[args[1]])
            work[res[0]] = sp.Piecewise((value, cond), (sp.Integer(0), True))
        else:
            raise LibraryError(
                expected(
                    "expr",
                    "operations with a sympy counterpart",
                    f"the CasADi operation {_OP_NAMES.get(op, op)}",
                    "rewrite the term with elementary functions, powers, sign, fabs, fmin/fmax or if_else",
                    raw=True,
                )
            )
    return out[0] if scalar else out


def _min_max(fun):
    return lambda *args: reduce(fun, args)


_SYMPY_FUNCTIONS = {
    sp.sin: ca.sin,
    sp.cos: ca.cos,
    sp.tan: ca.tan,
    sp.asin: ca.asin,
    sp.acos: ca.acos,
    sp.atan: ca.atan,
    sp.sinh: ca.sinh,
    sp.cosh: ca.cosh,
    sp.tanh: ca.tanh,
    sp.asinh: ca.asinh,
    sp.acosh: ca.acosh,
    sp.atanh: ca.atanh,
    sp.exp: ca.exp,
    sp.log: ca.log,
    sp.sign: ca.sign,
    sp.Abs: ca.fabs,
    sp.floor: ca.floor,
    sp.ceiling: ca.ceil,
    sp.erf: ca.erf,
    sp.atan2: ca.atan2,
    sp.Min: _min_max(ca.fmin),
    sp.Max: _min_max(ca.fmax),
    sp.StrictLessThan: ca.lt,
    sp.LessThan: ca.le,
    sp.StrictGreaterThan: ca.gt,
    sp.GreaterThan: ca.ge,
    sp.Eq: ca.eq,
    sp.Ne: ca.ne,
    sp.And: _min_max(ca.logic_and),
    sp.Or: _min_max(ca.logic_or),
    sp.Not: ca.logic_not,
}


def _pow(base: ca.SX, exponent: sp.Expr, convert) -> ca.SX:
    if exponent.is_Integer:
        n = int(exponent)
        if n == 0:
            return ca.SX(1)
        p = ca.constpow(base, abs(n))
        return p if n > 0 else 1 / p
    if exponent == sp.Rational(1, 2):
        return ca.sqrt(base)
    if exponent == -sp.Rational(1, 2):
        return 1 / ca.sqrt(base)
    if exponent.is_number:
        return ca.constpow(base, float(exponent))
    return ca.power(base, convert(exponent))


def sympy_to_casadi(expr: sp.Expr, symbols: Mapping[str, ca.SX]) -> ca.SX:
    """Convert a sympy expression to a CasADi SX expression by walking its tree.

    Parameters
    ----------
    expr : sympy.Expr
        Expression in sympy symbols; each symbol is looked up in ``symbols`` by name.
    symbols : mapping of str to ca.SX
        The CasADi symbol for each sympy symbol name.

    Returns
    -------
    ca.SX
        A scalar expression. Integer powers become ``constpow`` (exact for negative
        bases), ``Abs`` becomes ``fabs``, ``Piecewise`` a chain of ``if_else``.

    Raises
    ------
    LibraryError
        If a symbol is not in ``symbols`` or a function has no CasADi counterpart.

    Examples
    --------
    >>> import casadi as ca
    >>> import sympy as sp
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> a, b = sp.symbols("x1 x2", real=True)
    >>> expr = symsbl.sympy_to_casadi(sp.Abs(a) * b**3, {"x1": x1, "x2": x2})
    >>> float(ca.Function("f", [x1, x2], [expr])(-2.0, 3.0))
    54.0
    """
    if not isinstance(expr, sp.Basic):
        # Text would go through sympy's parser, which evaluates Python: refuse it.
        raise LibraryError(
            expected(
                "expr",
                "a sympy expression (parse text with symsbl's model files or --base)",
                type(expr).__name__,
                raw=True,
            )
        )
    cache: dict[sp.Basic, ca.SX] = {}

    def convert(e: sp.Basic) -> ca.SX:
        if e in cache:
            return cache[e]
        if e.is_Symbol:
            if e.name not in symbols:
                raise LibraryError(
                    expected(
                        "expr",
                        f"symbols among the declared variables {sorted(symbols)}",
                        e.name,
                        "declare it or rename it",
                    )
                )
            out = ca.SX(symbols[e.name])
        elif e is sp.true or e is sp.false:
            out = ca.SX(1.0 if e is sp.true else 0.0)
        elif e.is_Number or e.is_NumberSymbol:
            out = ca.SX(float(e))
        elif e.is_Add:
            out = reduce(lambda a, b: a + b, (convert(a) for a in e.args))
        elif e.is_Mul:
            out = reduce(lambda a, b: a * b, (convert(a) for a in e.args))
        elif e.is_Pow:
            out = _pow(convert(e.base), e.exp, convert)
        elif isinstance(e, sp.Piecewise):
            out = ca.SX(float("nan"))
            for value, cond in reversed(e.args):
                out = convert(value) if cond is sp.true else ca.if_else(convert(cond), convert(value), out)
        elif e.func in _SYMPY_FUNCTIONS:
            out = _SYMPY_FUNCTIONS[e.func](*(convert(a) for a in e.args))
        else:
            supported = ", ".join(["Add", "Mul", "Pow", "Piecewise"] + sorted(f.__name__ for f in _SYMPY_FUNCTIONS))
            raise LibraryError(
                expected("expr", f"functions with a CasADi counterpart ({supported})", e.func.__name__, raw=True)
            )
        cache[e] = out
        return out

    return convert(expr)


def is_smooth(expr) -> bool:
    """Whether expressions avoid non-smooth operations (sign, fabs, fmin, fmax, if_else, ...).

    Parameters
    ----------
    expr : ca.SX or list of ca.SX

    Returns
    -------
    bool
        False if any instruction is sign, fabs, fmin, fmax, a comparison, a logical
        operation, if_else, floor, ceil, copysign or fmod.
    """
    items, _ = _flatten(expr)
    return not uses_ops(items, NONSMOOTH_OPS)
