"""OdeSystem: states, inputs, parameters and a symbolic right-hand side ``x' = f(x, u; p)``.

One type serves truth models (:mod:`symsbl.systems`) and identified models alike: the right-hand side is
any CasADi SX expression in the state, input and parameter symbols.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from .._base.casadi import DISCONTINUOUS_OPS, NONSMOOTH_OPS, run_chunks, scalar_symbols, uses_ops
from .._base.errors import SimulationError, expected

__all__ = ["OdeSystem", "map_rows"]

_EVAL_CHUNK = 4096


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
        accepted too (sympy is converted by symbol name with :func:`symsbl.sympy_to_casadi`).
    parameters : tuple of ca.SX
        Scalar SX symbols that appear in ``rhs`` and have the values ``parameter_values``; they are
        substituted when the system is compiled, and :meth:`with_parameters` re-parameterises.
    parameter_values : tuple of float
    name : str
    outputs : tuple of (str, ca.SX)
        Measured channels that are not states, ``y = h(x, u; p)``, by name (an accelerometer is a velocity's
        right-hand side, a force cell any expression of the states and inputs): :func:`symsbl.simulate` returns
        them as columns after the states. A mapping ``{name: expression}`` is accepted.

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

    An accelerometer on the mass is the velocity's right-hand side, an output:

    >>> osc.with_outputs(a=osc.rhs[1]).output_names
    ('a',)
    """

    states: tuple
    inputs: tuple = ()
    rhs: tuple = ()
    parameters: tuple = ()
    parameter_values: tuple = ()
    name: str = "system"
    outputs: tuple = ()

    def __post_init__(self):
        states = scalar_symbols(self.states, "states", SimulationError)
        inputs = scalar_symbols(self.inputs, "inputs", SimulationError)
        params = scalar_symbols(self.parameters, "parameters", SimulationError)
        scalar_symbols(states + inputs + params, "states, inputs and parameters together", SimulationError)
        if len(self.parameter_values) != len(params):
            raise SimulationError(
                expected(
                    "parameter_values",
                    f"one value per parameter ({len(params)})",
                    f"{len(self.parameter_values)} values",
                    raw=True,
                )
            )
        values = tuple(float(v) for v in self.parameter_values)
        rhs = tuple(self._to_sx(e, states + inputs + params) for e in self.rhs)
        if len(rhs) != len(states):
            raise SimulationError(
                expected(
                    "rhs", f"one expression per state {[s.name() for s in states]}", f"{len(rhs)} expressions", raw=True
                )
            )
        known = {s.name() for s in states + inputs + params}
        free = sorted({s.name() for s in ca.symvar(ca.vertcat(*rhs))} - known) if rhs else []
        if free:
            raise SimulationError(
                expected(
                    "rhs",
                    f"expressions of the declared symbols {sorted(known)}",
                    f"expressions that also use {free}",
                    "declare them",
                    raw=True,
                )
            )
        outputs = self._outputs(states + inputs + params, known)
        for attr, val in (
            ("states", states),
            ("inputs", inputs),
            ("rhs", rhs),
            ("parameters", params),
            ("parameter_values", values),
            ("outputs", outputs),
        ):
            object.__setattr__(self, attr, val)

    def _outputs(self, symbols, known: set) -> tuple:
        """The outputs as ``((name, SX), ...)``, checked: distinct names unlike the symbols', declared symbols only."""
        raw = self.outputs.items() if isinstance(self.outputs, dict) else self.outputs
        out: list[tuple[str, ca.SX]] = []
        for item in raw:
            if not (isinstance(item, (tuple, list)) and len(item) == 2 and isinstance(item[0], str) and item[0]):
                raise SimulationError(
                    expected(
                        "outputs", "(name, expression) pairs or a mapping {name: expression}", repr(item)[:60], raw=True
                    )
                )
            name, expr = item
            if name in known or name in {n for n, _ in out} or name == "t":
                raise SimulationError(
                    expected(
                        "outputs", "names unlike the states', inputs', parameters' and each other's", name, raw=True
                    )
                )
            expr = self._to_sx(expr, symbols)
            free = sorted({s.name() for s in ca.symvar(expr)} - known)
            if free:
                raise SimulationError(
                    expected(
                        f"output {name!r}",
                        f"an expression of the declared symbols {sorted(known)}",
                        f"one that also uses {free}",
                        raw=True,
                    )
                )
            out.append((name, expr))
        return tuple(out)

    @staticmethod
    def _to_sx(expr, symbols) -> ca.SX:
        if isinstance(expr, (int, float, np.number)):
            return ca.SX(float(expr))
        if isinstance(expr, ca.SX):
            if not expr.is_scalar():
                raise SimulationError(expected("rhs", "scalar expressions", f"one of shape {expr.shape}", raw=True))
            return expr
        if type(expr).__module__.startswith("sympy"):
            from symsbl._symbolic.symbols import sympy_to_casadi

            return sympy_to_casadi(expr, {s.name(): s for s in symbols})
        raise SimulationError(expected("rhs", "CasADi SX, numbers or sympy expressions", type(expr).__name__, raw=True))

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
    def output_names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.outputs)

    @property
    def n_states(self) -> int:
        return len(self.states)

    @property
    def n_inputs(self) -> int:
        return len(self.inputs)

    @property
    def is_smooth(self) -> bool:
        """False if the right-hand side uses sign, abs, min/max, conditionals, floor/ceil or comparisons."""
        return not uses_ops(self.rhs, NONSMOOTH_OPS)

    @property
    def is_continuous(self) -> bool:
        """False if the right-hand side can jump (sign, conditionals, floor/ceil, comparisons); abs/min/max are
        kinks."""
        return not uses_ops(self.rhs, DISCONTINUOUS_OPS)

    def _symbols(self):
        return [ca.vertcat(*self.states), ca.vertcat(*self.inputs), ca.vertcat(*self.parameters)]

    def __repr__(self) -> str:
        return (
            f"OdeSystem(name={self.name!r}, states={self.state_names}, inputs={self.input_names}, "
            f"parameters={dict(zip(self.parameter_names, self.parameter_values))})"
        )

    # ------------------------------------------------------------------ symbolic forms
    def rhs_expr(self) -> ca.SX:
        """The right-hand side as an ``(n_states, 1)`` SX column with the parameter values substituted."""
        xdot = ca.vertcat(*self.rhs)
        if self.parameters:
            xdot = ca.substitute(xdot, ca.vertcat(*self.parameters), ca.DM(self.parameter_values))
        return xdot

    def rhs_function(self) -> ca.Function:
        """``ca.Function("rhs", [x (n_states, 1), u (n_inputs, 1)], [xdot (n_states, 1)])``, parameters substituted."""
        return ca.Function(
            "rhs", [ca.vertcat(*self.states), ca.vertcat(*self.inputs)], [self.rhs_expr()], ["x", "u"], ["xdot"]
        )

    def with_parameters(self, **values: float) -> OdeSystem:
        """Return a copy with some parameter values replaced, e.g. ``duffing().with_parameters(k3=2e9)``."""
        unknown = sorted(set(values) - set(self.parameter_names))
        if unknown:
            raise SimulationError(
                expected("parameters", f"names among {list(self.parameter_names)} of {self.name!r}", unknown)
            )
        new = tuple(float(values.get(n, v)) for n, v in zip(self.parameter_names, self.parameter_values))
        return OdeSystem(self.states, self.inputs, self.rhs, self.parameters, new, self.name, self.outputs)

    def with_outputs(self, **outputs) -> OdeSystem:
        """Return a copy with these outputs added, ``name=expression`` (e.g. ``a=system.rhs[1]``, an
        accelerometer on the velocity ``x2``)."""
        return OdeSystem(
            self.states,
            self.inputs,
            self.rhs,
            self.parameters,
            self.parameter_values,
            self.name,
            self.outputs + tuple(outputs.items()),
        )

    def output_function(self) -> ca.Function:
        """``ca.Function("outputs", [x, u, p], [y (n_outputs, 1)])``, the parameters an input."""
        return ca.Function(
            "outputs", self._symbols(), [ca.vertcat(*[e for _, e in self.outputs])], ["x", "u", "p"], ["y"]
        )

    def evaluate_outputs(self, X, U=None, parameters=None) -> np.ndarray:
        """The outputs on samples ``X`` ``(n_samples, n_states)`` and ``U``, at the parameter values (or the
        ``parameters`` given): ``(n_samples, n_outputs)``."""
        X = np.ascontiguousarray(np.atleast_2d(np.asarray(X, dtype=float)))
        n = X.shape[0]
        U = np.zeros((n, self.n_inputs)) if U is None else np.asarray(U, dtype=float).reshape(n, self.n_inputs)
        p = np.asarray(self.parameter_values if parameters is None else parameters, dtype=float)
        P = np.ascontiguousarray(np.broadcast_to(p, (n, p.size)))
        return map_rows(self.output_function(), [X, np.ascontiguousarray(U), P], len(self.outputs))

    def to_sympy(self, *, substitute: bool = True) -> list:
        """The equations as ``sympy.Eq(Derivative(x_i, t), f_i)``, one per state.

        Parameters
        ----------
        substitute : bool
            Substitute the parameter values (default) or keep the parameters as symbols.
        """
        import sympy as sp

        from symsbl._symbolic.symbols import casadi_to_sympy

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
            raise SimulationError(expected("X", f"shape (n_samples, {self.n_states})", f"shape {X.shape}", raw=True))
        n = X.shape[0]
        if U is None:
            U = np.zeros((n, self.n_inputs))
        U = np.asarray(U, dtype=float)
        if U.ndim == 1 and self.n_inputs == 1:
            U = U[:, None]
        U = np.ascontiguousarray(U)
        if U.shape != (n, self.n_inputs):
            raise SimulationError(expected("U", f"shape ({n}, {self.n_inputs})", f"shape {U.shape}", raw=True))
        return map_rows(self.rhs_function(), [X, U], self.n_states)


def map_rows(f: ca.Function, args: list[np.ndarray], n_out: int, chunk: int = _EVAL_CHUNK) -> np.ndarray:
    """Evaluate a column-vector Function ``f`` row by row over C-contiguous ``(n, k_i)`` arrays, in chunks."""
    n = args[0].shape[0]
    size = max(1, min(chunk, n))
    out = np.empty((n, n_out))
    run_chunks(f.map(size), size, [np.ascontiguousarray(a) for a in args], [out])
    return out
