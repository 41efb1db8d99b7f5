"""OdeSystem: states, inputs, parameters and a symbolic right-hand side ``x' = f(x, u; p)``.

One type serves truth models (:mod:`symsbl.systems`) and identified models alike: the right-hand side is
any CasADi SX expression in the state, input and parameter symbols.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from symsbl.errors import SimulationError

__all__ = ["OdeSystem", "NONSMOOTH_OPS", "DISCONTINUOUS_OPS", "is_smooth_expr"]

#: CasADi operations whose value or slope jumps: a right-hand side using any of them is not smooth.
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

_EVAL_CHUNK = 4096


def is_smooth_expr(exprs, inputs, ops=NONSMOOTH_OPS) -> bool:
    """True if no operation in ``exprs`` (SX, functions of the SX symbols ``inputs``) is in ``ops``."""
    f = ca.Function("smooth_check", list(inputs), [ca.vertcat(*exprs)])
    return not any(f.instruction_id(k) in ops for k in range(f.n_instructions()))


def _scalar_symbols(symbols, what: str) -> tuple[ca.SX, ...]:
    out = tuple(symbols)
    for s in out:
        if not isinstance(s, ca.SX) or not s.is_scalar() or not s.is_symbolic():
            raise SimulationError(
                f"{what} must be scalar SX symbols (e.g. ca.SX.sym('x1')); received {s!r}. "
                "Create one symbol per variable."
            )
    names = [s.name() for s in out]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise SimulationError(f"{what} names must be unique; {dupes} appear more than once.")
    return out


@dataclass(frozen=True, eq=False)
class OdeSystem:
    """An explicit ODE ``x' = f(x, u; p)`` with named scalar SX symbols.

    Parameters
    ----------
    states : tuple of ca.SX
        Scalar SX symbols, one per state, e.g. ``(x1, x2)``.
    inputs : tuple of ca.SX
        Scalar SX symbols of the inputs (may be empty).
    rhs : tuple of ca.SX
        One scalar expression per state: its time derivative. Numbers and sympy expressions are
        accepted too (sympy is converted by symbol name with :func:`symsbl.symbolic.sympy_to_casadi`).
    parameters : tuple of ca.SX
        Scalar SX symbols that appear in ``rhs`` and have the values ``parameter_values``; they are
        substituted when the system is compiled, and :meth:`with_parameters` re-parameterises.
    parameter_values : tuple of float
    name : str

    Raises
    ------
    SimulationError
        If symbols are not scalar SX symbols, names repeat, ``rhs`` has the wrong length, a value is
        missing, or ``rhs`` depends on a symbol that is not a state, input or parameter.

    Examples
    --------
    A mass-spring-damper with named parameters:

    >>> import casadi as ca
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> m, c, k = symsbl.symbols("m c k")
    >>> osc = symsbl.OdeSystem((x1, x2), (F,), (x2, (F - c * x2 - k * x1) / m), (m, c, k), (1.0, 20.0, 1e4),
    ...                        name="oscillator")
    >>> osc.to_sympy()
    [Eq(Derivative(x1, t), x2), Eq(Derivative(x2, t), F - 10000*x1 - 20*x2)]
    >>> osc.with_parameters(c=40.0).to_sympy()[1]
    Eq(Derivative(x2, t), F - 10000*x1 - 40*x2)
    """

    states: tuple
    inputs: tuple = ()
    rhs: tuple = ()
    parameters: tuple = ()
    parameter_values: tuple = ()
    name: str = "system"

    def __post_init__(self):
        states = _scalar_symbols(self.states, "states")
        inputs = _scalar_symbols(self.inputs, "inputs")
        params = _scalar_symbols(self.parameters, "parameters")
        _scalar_symbols(states + inputs + params, "states, inputs and parameters together")
        if len(self.parameter_values) != len(params):
            raise SimulationError(
                f"parameter_values must give one value per parameter ({len(params)}); "
                f"received {len(self.parameter_values)}."
            )
        values = tuple(float(v) for v in self.parameter_values)
        rhs = tuple(self._to_sx(e, states + inputs + params) for e in self.rhs)
        if len(rhs) != len(states):
            raise SimulationError(
                f"rhs must have one expression per state ({len(states)}: {[s.name() for s in states]}); "
                f"received {len(rhs)}."
            )
        known = {s.name() for s in states + inputs + params}
        free = sorted({s.name() for s in ca.symvar(ca.vertcat(*rhs))} - known) if rhs else []
        if free:
            raise SimulationError(
                f"rhs depends on {free}, which are not states, inputs or parameters of {self.name!r}; "
                f"declare them (known symbols: {sorted(known)})."
            )
        for attr, val in (("states", states), ("inputs", inputs), ("rhs", rhs), ("parameters", params),
                          ("parameter_values", values)):
            object.__setattr__(self, attr, val)

    @staticmethod
    def _to_sx(expr, symbols) -> ca.SX:
        if isinstance(expr, (int, float, np.number)):
            return ca.SX(float(expr))
        if isinstance(expr, ca.SX):
            if not expr.is_scalar():
                raise SimulationError(f"each rhs entry must be a scalar expression; received shape {expr.shape}.")
            return expr
        if type(expr).__module__.startswith("sympy"):
            from symsbl.symbolic import sympy_to_casadi

            return sympy_to_casadi(expr, {s.name(): s for s in symbols})
        raise SimulationError(f"rhs entries must be CasADi SX, numbers or sympy expressions; received {type(expr)}.")

    # ------------------------------------------------------------------ descriptions
    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(s.name() for s in self.states)

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(s.name() for s in self.inputs)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(s.name() for s in self.parameters)

    @property
    def n_states(self) -> int:
        return len(self.states)

    @property
    def n_inputs(self) -> int:
        return len(self.inputs)

    @property
    def is_smooth(self) -> bool:
        """False if the right-hand side uses sign, abs, min/max, conditionals, floor/ceil or comparisons."""
        return is_smooth_expr(self.rhs, self._symbols())

    @property
    def is_continuous(self) -> bool:
        """False if the right-hand side can jump (sign, conditionals, floor/ceil, comparisons); abs/min/max are kinks."""
        return is_smooth_expr(self.rhs, self._symbols(), DISCONTINUOUS_OPS)

    def _symbols(self):
        return [ca.vertcat(*self.states), ca.vertcat(*self.inputs), ca.vertcat(*self.parameters)]

    def __repr__(self) -> str:
        return (f"OdeSystem(name={self.name!r}, states={self.state_names}, inputs={self.input_names}, "
                f"parameters={dict(zip(self.parameter_names, self.parameter_values))})")

    # ------------------------------------------------------------------ symbolic forms
    def rhs_expr(self) -> ca.SX:
        """The right-hand side as an ``(n_states, 1)`` SX column with the parameter values substituted."""
        xdot = ca.vertcat(*self.rhs)
        if self.parameters:
            xdot = ca.substitute(xdot, ca.vertcat(*self.parameters), ca.DM(self.parameter_values))
        return xdot

    def rhs_function(self) -> ca.Function:
        """``ca.Function("rhs", [x (n_states, 1), u (n_inputs, 1)], [xdot (n_states, 1)])``, parameters substituted."""
        return ca.Function("rhs", [ca.vertcat(*self.states), ca.vertcat(*self.inputs)], [self.rhs_expr()],
                           ["x", "u"], ["xdot"])

    def with_parameters(self, **values: float) -> OdeSystem:
        """Return a copy with some parameter values replaced, e.g. ``duffing().with_parameters(k3=2e9)``."""
        unknown = sorted(set(values) - set(self.parameter_names))
        if unknown:
            raise SimulationError(f"unknown parameters {unknown}; {self.name!r} has {list(self.parameter_names)}.")
        new = tuple(float(values.get(n, v)) for n, v in zip(self.parameter_names, self.parameter_values))
        return OdeSystem(self.states, self.inputs, self.rhs, self.parameters, new, self.name)

    def to_sympy(self, *, substitute: bool = True) -> list:
        """The equations as ``sympy.Eq(Derivative(x_i, t), f_i)``, one per state.

        Parameters
        ----------
        substitute : bool
            Substitute the parameter values (default) or keep the parameters as symbols.
        """
        import sympy as sp

        from symsbl.symbolic import casadi_to_sympy

        exprs = [ca.vertcat(*self.rhs)[i] for i in range(self.n_states)]
        if substitute:
            exprs = [self.rhs_expr()[i] for i in range(self.n_states)]
        rhs = casadi_to_sympy(exprs)
        t = sp.Symbol("t", real=True)
        return [sp.Eq(sp.Derivative(sp.Symbol(n, real=True), t), r) for n, r in zip(self.state_names, rhs)]

    # ------------------------------------------------------------------ numbers
    def evaluate_rhs(self, X, U=None) -> np.ndarray:
        """Evaluate the right-hand side on samples.

        Parameters
        ----------
        X : array_like, shape (n_samples, n_states)
        U : array_like, shape (n_samples, n_inputs), optional (omit when ``n_inputs == 0``)

        Returns
        -------
        ndarray, shape (n_samples, n_states)
        """
        X = np.ascontiguousarray(np.atleast_2d(np.asarray(X, dtype=float)))
        if X.ndim != 2 or X.shape[1] != self.n_states:
            raise SimulationError(f"X must have shape (n_samples, {self.n_states}); received {X.shape}.")
        n = X.shape[0]
        if U is None:
            U = np.zeros((n, self.n_inputs))
        U = np.asarray(U, dtype=float)
        if U.ndim == 1 and self.n_inputs == 1:
            U = U[:, None]
        U = np.ascontiguousarray(U)
        if U.shape != (n, self.n_inputs):
            raise SimulationError(f"U must have shape ({n}, {self.n_inputs}); received {U.shape}.")
        return map_rows(self.rhs_function(), [X, U], self.n_states)


def map_rows(f: ca.Function, args: list[np.ndarray], n_out: int, chunk: int = _EVAL_CHUNK) -> np.ndarray:
    """Evaluate a column-vector Function ``f`` row by row over C-contiguous ``(n, k_i)`` arrays, in chunks.

    A ``(k, chunk)`` CasADi matrix is column-major, i.e. the same memory as a C-ordered ``(chunk, k)``
    array, so ``Function.buffer()`` reads and writes the numpy rows in place.
    """
    n = args[0].shape[0]
    size = max(1, min(chunk, n))
    fm = f.map(size)
    out = np.empty((n, n_out))
    full = n - n % size
    if full:
        buf, trigger = fm.buffer()
        for k0 in range(0, full, size):
            views = [np.ascontiguousarray(a[k0:k0 + size]) for a in args]
            res = out[k0:k0 + size]
            for i, v in enumerate(views):
                buf.set_arg(i, memoryview(v))
            buf.set_res(0, memoryview(res))
            trigger()
    if full < n:
        rest = n - full
        pad = [np.zeros((size, a.shape[1])) for a in args]
        for p, a in zip(pad, args):
            p[:rest] = a[full:]
        res = np.empty((size, n_out))
        buf, trigger = fm.buffer()
        for i, p in enumerate(pad):
            buf.set_arg(i, memoryview(p))
        buf.set_res(0, memoryview(res))
        trigger()
        out[full:] = res[:rest]
    return out
