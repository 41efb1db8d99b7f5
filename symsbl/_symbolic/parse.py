"""Term expressions read from text as data: a whitelist grammar, never ``eval`` or ``sympify``.

Model files travel between people, and ``--base`` strings come from the command line; both
hold expressions such as ``x1**2*Abs(x2)`` or ``sign(x2)``. Handing such text to Python
(``eval``) or to sympy's parser (``sympify``, which evaluates Python) would run whatever a
hostile file contains. This module tokenises the text itself and builds CasADi SX expressions
from a fixed grammar, the one sympy's ``str`` prints for the terms symsbl makes::

    expr     := or_expr
    or_expr  := and_expr ('|' and_expr)*
    and_expr := not_expr ('&' not_expr)*
    not_expr := '~' not_expr | compare
    compare  := sum (('<' | '<=' | '>' | '>=' | '==' | '!=') sum)?
    sum      := product (('+' | '-') product)*
    product  := unary (('*' | '/') unary)*
    unary    := ('-' | '+') unary | power
    power    := atom ('**' unary)?                 (right-associative: a**b**c = a**(b**c))
    atom     := NUMBER | NAME | NAME '(' args ')' | '(' expr ')'

Names are the declared variables (states and inputs), the constants ``pi`` and ``E``,
``True``/``False``, and the functions of :data:`FUNCTIONS` (``Piecewise((value, condition),
...)`` included). Anything else is an error that names the offending text and its position.
The text is limited to :data:`MAX_LENGTH` characters and :data:`MAX_DEPTH` levels of nesting,
so no input can exhaust memory or the stack.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from functools import reduce

import casadi as ca

from .._base.errors import ExpressionError, expected

__all__ = ["parse_expression", "FUNCTIONS", "MAX_LENGTH", "MAX_DEPTH"]

#: Longest expression text accepted (characters).
MAX_LENGTH = 10_000
#: Deepest nesting of parentheses and unary operators accepted (each level costs about ten Python frames).
MAX_DEPTH = 50


def _min_max(fun):
    def apply(*args):
        if len(args) < 2:
            raise ExpressionError(f"expected at least 2 arguments, received {len(args)}")
        return reduce(fun, args)

    return apply


#: Functions a term may call, by the name sympy prints, and their CasADi counterparts.
FUNCTIONS = {
    "sin": ca.sin,
    "cos": ca.cos,
    "tan": ca.tan,
    "asin": ca.asin,
    "acos": ca.acos,
    "atan": ca.atan,
    "sinh": ca.sinh,
    "cosh": ca.cosh,
    "tanh": ca.tanh,
    "asinh": ca.asinh,
    "acosh": ca.acosh,
    "atanh": ca.atanh,
    "exp": ca.exp,
    "log": ca.log,
    "sqrt": ca.sqrt,
    "Abs": ca.fabs,
    "abs": ca.fabs,
    "sign": ca.sign,
    "floor": ca.floor,
    "ceiling": ca.ceil,
    "erf": ca.erf,
    "erfinv": ca.erfinv,
    "atan2": ca.atan2,
    "Min": _min_max(ca.fmin),
    "Max": _min_max(ca.fmax),
    "Eq": ca.eq,
    "Ne": ca.ne,
}
_ARITY = {"atan2": 2, "Eq": 2, "Ne": 2, "Min": None, "Max": None}
_CONSTANTS = {"pi": 3.141592653589793, "E": 2.718281828459045, "True": 1.0, "False": 0.0}
_COMPARE = {"<": ca.lt, "<=": ca.le, ">": ca.gt, ">=": ca.ge, "==": ca.eq, "!=": ca.ne}

_TOKEN = re.compile(
    r"\s*(?:(?P<number>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"
    r"|(?P<name>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<op>\*\*|<=|>=|==|!=|[-+*/()<>,&|~]))"
)


def _tokens(text: str, where: str) -> list[tuple[str, str, int]]:
    out, pos = [], 0
    while pos < len(text):
        if text[pos:].strip() == "":
            break
        m = _TOKEN.match(text, pos)
        if m is None:
            bad = text[pos:].lstrip()[:1]
            at = len(text) - len(text[pos:].lstrip())
            raise ExpressionError(
                f"{where}: expected a term such as x1**2*Abs(x2), received {text!r}: the character {bad!r} at "
                f"position {at} is not part of the grammar; use numbers, the variable names, + - * / ** and "
                "the listed functions"
            )
        kind = m.lastgroup
        assert kind is not None  # every alternative of _TOKEN is a named group
        out.append((kind, m.group(kind), m.start(kind)))
        pos = m.end()
    out.append(("end", "", len(text)))
    return out


class _Parser:
    """Recursive-descent parser over the token list; builds SX as it goes."""

    def __init__(self, text: str, symbols: Mapping[str, ca.SX], where: str):
        self.text, self.symbols, self.where = text, symbols, where
        self.toks = _tokens(text, where)
        self.i = 0
        self.depth = 0

    # -- helpers ------------------------------------------------------------------------------
    def error(self, what: str) -> ExpressionError:
        kind, value, pos = self.toks[self.i]
        found = "the end of the text" if kind == "end" else f"{value!r} at position {pos}"
        return ExpressionError(f"{self.where}: expected {what} in {self.text!r}, received {found}")

    def peek(self) -> str:
        kind, value, _ = self.toks[self.i]
        return value if kind == "op" else kind

    def take(self, op: str) -> bool:
        if self.peek() == op:
            self.i += 1
            return True
        return False

    def expect(self, op: str) -> None:
        if not self.take(op):
            raise self.error(f"{op!r}")

    def nested(self, rule):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise ExpressionError(
                expected(
                    self.where,
                    f"at most {MAX_DEPTH} levels of nesting",
                    "deeper text",
                    "simplify the expression",
                    raw=True,
                )
            )
        try:
            return rule()
        finally:
            self.depth -= 1

    def finite(self, value: ca.SX, divisor: ca.SX | None = None) -> ca.SX:
        """``value``, unless it is a constant that is not finite (``1e999``, ``log(0)``, ``0**-1``) or divides by
        a constant zero."""
        if divisor is not None and divisor.is_constant() and float(divisor) == 0.0:
            why = "divides by zero"
        elif value.is_constant() and not math.isfinite(float(value)):
            why = f"holds the constant {float(value)!r}"
        else:
            return value
        raise ExpressionError(
            expected(
                self.where,
                "a term that is finite where its variables are",
                f"{self.text!r}, which {why}",
                "correct or remove the term",
                raw=True,
            )
        )

    # -- grammar ------------------------------------------------------------------------------
    def parse(self) -> ca.SX:
        value = self.expr()
        if self.toks[self.i][0] != "end":
            raise self.error("an operator or the end of the term")
        return value

    def expr(self) -> ca.SX:
        return self.nested(self.or_expr)

    def or_expr(self):
        value = self.and_expr()
        while self.take("|"):
            value = ca.logic_or(value, self.and_expr())
        return value

    def and_expr(self):
        value = self.not_expr()
        while self.take("&"):
            value = ca.logic_and(value, self.not_expr())
        return value

    def not_expr(self):
        if self.take("~"):
            return ca.logic_not(self.nested(self.not_expr))
        return self.compare()

    def compare(self):
        value = self.sum()
        op = self.peek()
        if op in _COMPARE:
            self.i += 1
            value = _COMPARE[op](value, self.sum())
        return value

    def sum(self):
        value = self.product()
        while self.peek() in ("+", "-"):
            op = self.toks[self.i][1]
            self.i += 1
            rhs = self.product()
            value = value + rhs if op == "+" else value - rhs
        return value

    def product(self):
        value = self.unary()
        while self.peek() in ("*", "/"):
            op = self.toks[self.i][1]
            self.i += 1
            rhs = self.unary()
            value = self.finite(value * rhs) if op == "*" else self.finite(value / rhs, divisor=rhs)
        return value

    def unary(self):
        if self.take("-"):
            return -self.nested(self.unary)
        if self.take("+"):
            return self.nested(self.unary)
        return self.power()

    def power(self):
        base = self.atom()
        if self.take("**"):
            exponent = self.nested(self.unary)
            return self.finite(_pow(base, exponent))
        return base

    def atom(self):
        kind, value, _ = self.toks[self.i]
        if kind == "number":
            self.i += 1
            return self.finite(ca.SX(float(value)))
        if self.take("("):
            inner = self.expr()
            self.expect(")")
            return inner
        if kind != "name":
            raise self.error("a number, a variable name, a function call or '('")
        self.i += 1
        if self.peek() == "(":
            return self.call(value)
        if value in self.symbols:
            return ca.SX(self.symbols[value])
        if value in _CONSTANTS:
            return ca.SX(_CONSTANTS[value])
        self.i -= 1
        raise self.error(f"a variable among {sorted(self.symbols)} or a constant (pi, E)")

    def call(self, name: str):
        if name == "Piecewise":
            return self.piecewise()
        if name not in FUNCTIONS:
            self.i -= 1
            raise self.error(f"a function among {sorted(FUNCTIONS) + ['Piecewise']}")
        self.expect("(")
        args = [self.expr()]
        while self.take(","):
            args.append(self.expr())
        self.expect(")")
        arity = _ARITY.get(name, 1)
        if arity is not None and len(args) != arity:
            raise ExpressionError(
                f"{self.where}: expected {arity} argument(s) to {name} in {self.text!r}, received {len(args)}"
            )
        try:
            return self.finite(FUNCTIONS[name](*args))
        except ExpressionError as err:
            if str(err).startswith(self.where):
                raise
            raise ExpressionError(f"{self.where}: {name} in {self.text!r}: {str(err)}") from None

    def piecewise(self):
        self.expect("(")
        pieces = [self.piece()]
        while self.take(","):
            pieces.append(self.piece())
        self.expect(")")
        out = ca.SX(float("nan"))
        for value, cond in reversed(pieces):
            out = ca.if_else(cond, value, out)
        return out

    def piece(self):
        self.expect("(")
        value = self.expr()
        self.expect(",")
        cond = self.expr()
        self.expect(")")
        return value, cond


def _pow(base: ca.SX, exponent: ca.SX) -> ca.SX:
    """Integer powers as ``constpow`` (exact for negative bases), 1/2 as ``sqrt``, others ``power``."""
    if exponent.is_constant():
        p = float(exponent)
        if p.is_integer() and abs(p) <= 1e6:
            n = int(p)
            if n == 0:
                return ca.SX(1)
            value = ca.constpow(base, abs(n))
            return value if n > 0 else 1 / value
        if p == 0.5:
            return ca.sqrt(base)
        if p == -0.5:
            return 1 / ca.sqrt(base)
        return ca.constpow(base, p)
    return ca.power(base, exponent)


def parse_expression(text: str, symbols: Mapping[str, ca.SX], *, where: str = "expression") -> ca.SX:
    """Build a scalar CasADi SX expression from ``text`` without evaluating any code.

    Parameters
    ----------
    text : str
        An expression in the grammar of the module docstring, e.g. ``"x1**2*Abs(x2)"``.
    symbols : mapping of str to ca.SX
        The variables the expression may use, by name.
    where : str
        What the text is, for error messages (e.g. ``"model JSON: equation 'x2', term 3"``).

    Returns
    -------
    ca.SX
        A scalar expression of ``symbols``.

    Raises
    ------
    ExpressionError
        On anything outside the grammar: unknown names, attribute access, strings, brackets,
        text longer than :data:`MAX_LENGTH` or nested deeper than :data:`MAX_DEPTH`.

    Examples
    --------
    >>> import casadi as ca
    >>> x1, x2 = ca.SX.sym("x1"), ca.SX.sym("x2")
    >>> e = parse_expression("x1**2*Abs(x2) - 3.5e-2*sign(x2)", {"x1": x1, "x2": x2})
    >>> float(ca.Function("f", [x1, x2], [e])(2.0, -3.0))
    12.035
    >>> parse_expression("__import__('os')", {"x1": x1})
    Traceback (most recent call last):
    ...
    symsbl.ExpressionError: expression: expected a term such as x1**2*Abs(x2), received "__import__('os')": the
    character "'" at position 11 is not part of the grammar; use numbers, the variable names, + - * / ** and the
    listed functions
    """
    if not isinstance(text, str):
        raise ExpressionError(f"{where}: expected a string such as 'x1**2', received {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise ExpressionError(
            f"{where}: expected at most {MAX_LENGTH} characters, received {len(text)}; shorten the expression"
        )
    if not text.strip():
        raise ExpressionError(f"{where}: expected an expression such as 'x1**2', received an empty string")
    try:
        return _Parser(text, symbols, where).parse()
    except RecursionError:  # a guard behind MAX_DEPTH, for a caller already deep in its own stack
        raise ExpressionError(
            expected(
                where, f"at most {MAX_DEPTH} levels of nesting", "deeper text", "simplify the expression", raw=True
            )
        ) from None
