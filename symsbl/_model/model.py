"""The identified model: posterior per equation, rendered as a symbolic ODE.

An :class:`IdentifiedModel` holds, for each state equation ``x_k' = sum_i beta_i d_i(x, u)``, the kept candidate
terms (CasADi expressions, the single source of truth for names and sympy forms), their posterior means, standard
deviations and covariance, prior precisions, the noise variance and the log evidence. It renders as

- a readable print with uncertainties, ``x2' = 1.000(0.001) F - 1.0000e4(3) x1 - ...``;
- a sympy system (``to_sympy``, ``to_latex``, ``_repr_latex_``);
- a CasADi :class:`~symsbl.OdeSystem` whose coefficients are parameters, ready to simulate;
- JSON (``to_json`` / ``from_json``, ``save`` / ``load``), the format the command line writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import sympy as sp

from .._base.errors import ParameterError, expected
from .._base.format import pretty
from .._simulation.ode import OdeSystem
from .estimates import Equation, FitMethod
from .modelfile import load_model, model_from_json, model_to_json, save_model
from .outputs import Output, latent_of, state_outputs
from .path import ModelPath

__all__ = ["IdentifiedModel"]


@dataclass(frozen=True)
class IdentifiedModel:
    """An identified system of ODEs, one :class:`Equation` per state.

    Attributes
    ----------
    states, inputs : tuple of casadi.SX
        Scalar symbols of the states (in equation order) and of the inputs.
    equations : tuple of Equation
        One per state, same order as ``states``, then one per algebraic output (``Equation.algebraic``: a
        channel with an equation of its own, such as a force cell).
    metadata : dict
        Free-form provenance (derivative strategy, library size, sample rate ...).
    fit : FitMethod
        Equation error (regression of the state derivatives) or output error (simulation error of the
        measured states, :func:`symsbl.refine`).
    kinematics : tuple of (str, str)
        Declared position-velocity pairs ``(x, v)``: ``x' = v`` holds exactly (a fixed equation).
    measured : tuple of str or None
        The states measured in the data the model was fitted on (None: all of them).
    joint_covariance : ndarray or None
        Posterior covariance of all coefficients in :meth:`parameters` order when the equations
        were estimated together (output error couples them); None for independent equations.
    path : ModelPath
        The candidate structures the model was chosen from, simplest first, with their evidence and
        cross-validated free-run error (empty when no choice was made).
    outputs : tuple of Output
        What each channel of the records is (:class:`~symsbl.StateOutput`, :class:`~symsbl.AccelerationOutput`,
        :class:`~symsbl.AlgebraicOutput`); empty: the states of :attr:`measured` as they are (see
        :attr:`observation`).

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify(train, library)
    >>> model.to_sympy()[1].lhs
    Derivative(x2(t), t)
    >>> "dot{x_{2}} &= 1.0 F" in model.to_latex(digits=3)
    True

    It saves to JSON and comes back with the same equations:

    >>> import os, tempfile
    >>> path = os.path.join(tempfile.mkdtemp(), "duffing.json")
    >>> model.save(path)
    >>> str(symsbl.IdentifiedModel.load(path)) == str(model)
    True
    >>> model.to_system().state_names  # an OdeSystem to simulate
    ('x1', 'x2')
    """

    states: tuple[ca.SX, ...]
    inputs: tuple[ca.SX, ...]
    equations: tuple[Equation, ...]
    metadata: dict = field(default_factory=dict, compare=False)
    fit: FitMethod = FitMethod.EQUATION_ERROR
    kinematics: tuple = ()
    measured: tuple | None = None
    joint_covariance: np.ndarray | None = field(default=None, compare=False, repr=False)
    path: ModelPath = field(default_factory=ModelPath, compare=False, repr=False)
    outputs: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "fit", FitMethod(self.fit))
        object.__setattr__(self, "kinematics", tuple(tuple(p) for p in self.kinematics))
        if self.measured is not None:
            object.__setattr__(self, "measured", tuple(self.measured))
        object.__setattr__(self, "outputs", tuple(self.outputs))

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the states."""
        return tuple(s.name() for s in self.states)

    @property
    def input_names(self) -> tuple[str, ...]:
        """Names of the inputs."""
        return tuple(u.name() for u in self.inputs)

    @property
    def observation(self) -> tuple[Output, ...]:
        """What each channel of the records is: :attr:`outputs`, or the measured states as they are."""
        return self.outputs if self.outputs else state_outputs(self.measured_names)

    @property
    def output_names(self) -> tuple[str, ...]:
        """The columns the model was fitted to (its outputs)."""
        return tuple(o.name for o in self.observation)

    def equation(self, lhs: str) -> Equation:
        """The equation of the state (or algebraic output) called ``lhs``."""
        for eq in self.equations:
            if eq.lhs == lhs:
                return eq
        raise ParameterError(expected("lhs", f"one of the equations {[eq.lhs for eq in self.equations]}", lhs))

    def __str__(self) -> str:
        lines = [str(eq) for eq in self.equations]
        for o in self.observation:
            if o.kind == "acceleration":
                lines.append(f"{o.name}: measures {o.equation}' (acceleration)")
        for name in self.latent_names:
            lines.append(f"{name}: latent (not measured); {self.convention(name)}")
        return "\n".join(lines)

    @property
    def latent_names(self) -> tuple[str, ...]:
        """States that no output observes, neither directly nor through their position-velocity pair: their
        equations were found, and their trajectories simulated, with no record of them."""
        return latent_of(self.state_names, self.observation, self.kinematics)

    def convention(self, name: str) -> str:
        """How the scale (and sign) of the latent state ``name`` is fixed.

        ``z`` and ``s z`` give the same measured output when every term that uses ``z`` is homogeneous in it
        (``|V| z |z|``, ``Max(0, z)``) and free to take the factor ``s`` that keeps its equation: the scale is then
        fixed by a coefficient held fixed that cannot take it (``z`` in another equation, or a term of ``z'`` of
        degree other than 1 in ``z``, such as its input term), or by the form of a term that is not homogeneous
        in ``z`` (``eta (Y - u)``, ``tanh(z / eps)``).

        Parameters
        ----------
        name : str
            A latent state (see :attr:`latent_names`).

        Returns
        -------
        str
            One line: how its scale is fixed, or that it is not (or not needed).
        """
        using = [(eq, t) for eq in self.equations for t in eq.terms if name in {s.name for s in t.sympy.free_symbols}]
        if not using:
            return "not needed: no equation uses it (nothing hidden)"
        own = [
            (eq, t) for eq in self.equations if eq.lhs == name and not eq.algebraic and not eq.fixed for t in eq.terms
        ]
        candidates = [(eq, t) for eq, t in using if t.name == name] + using + own
        for eq, t in candidates:
            degree = _degree(t.sympy, name)
            if t.fixed and degree != (1.0 if (eq.lhs == name and not eq.algebraic) else 0.0):
                if t.name == name:
                    return f"scaled so that its coefficient in {eq.lhs}' is {t.coef:g}"
                return f"scaled so that the term {pretty(t.name)} of {eq.written} has the coefficient {t.coef:g}"
        for eq, t in using:
            if _degree(t.sympy, name) is None:
                return f"its scale is fixed by the form of the term {pretty(t.name)} of {eq.written}"
        return "its scale is not fixed by a term of the model"

    # -- symbolic forms -------------------------------------------------------------------
    def to_sympy(self) -> list[sp.Eq]:
        """The system as sympy equations ``Eq(Derivative(x(t), t), rhs)``."""
        t = sp.Symbol("t", real=True)
        out = []
        for eq in self.equations:
            lhs = sp.Function(eq.lhs)(t) if eq.algebraic else sp.Derivative(sp.Function(eq.lhs)(t), t)
            out.append(sp.Eq(lhs, eq.rhs_sympy(), evaluate=False))
        return out

    def to_latex(self, digits: int = 4) -> str:
        """LaTeX of the system, coefficients rounded to ``digits`` significant digits."""
        lines = []
        for eq in self.equations:
            rhs = sp.Add(*[sp.Float(t.coef, digits) * t.sympy for t in eq.terms])
            lhs = sp.latex(sp.Symbol(eq.lhs))
            lhs = lhs if eq.algebraic else r"\dot{" + lhs + "}"
            lines.append(rf"{lhs} &= {sp.latex(rhs)}")
        return r"\begin{aligned}" + r" \\ ".join(lines) + r"\end{aligned}"

    def _repr_latex_(self) -> str:
        return "$" + self.to_latex() + "$"

    def parameters(self) -> tuple[list[ca.SX], np.ndarray]:
        """Coefficient symbols ``c_<state>_<i>`` and their posterior means."""
        syms, values = [], []
        for eq in self.equations:
            for i, t in enumerate(eq.terms):
                syms.append(ca.SX.sym(f"c_{eq.lhs}_{i}"))
                values.append(t.coef)
        return syms, np.array(values)

    @property
    def measured_names(self) -> tuple[str, ...]:
        """The states measured as they are when the model was fitted (all of them unless :attr:`measured` or
        :attr:`outputs` say otherwise)."""
        if self.outputs:
            return tuple(o.state for o in self.outputs if o.state is not None)
        return self.state_names if self.measured is None else self.measured

    def covariance(self) -> np.ndarray:
        """Posterior covariance of all coefficients, in ``parameters`` order: the joint one of an
        output-error fit, else block-diagonal (one block per equation)."""
        from scipy.linalg import block_diag

        if self.joint_covariance is not None:
            return np.asarray(self.joint_covariance)
        blocks = [np.atleast_2d(eq.covariance) for eq in self.equations if eq.terms]
        return block_diag(*blocks) if blocks else np.zeros((0, 0))

    def to_system(self, name: str = "identified") -> OdeSystem:
        """The model as a CasADi :class:`~symsbl.OdeSystem` with the coefficients as
        parameters (values: the posterior means) and the outputs that are not states (accelerations,
        algebraic outputs) as its outputs."""

        syms, values = self.parameters()
        rows, k = {}, 0
        for eq in self.equations:
            expr = ca.SX(0)
            for t in eq.terms:
                expr = expr + syms[k] * t.expr
                k += 1
            rows[eq.lhs] = expr
        states = dict(zip(self.state_names, self.states))
        outputs = tuple((o.name, o.expression(states, rows)) for o in self.observation if o.state is None)
        return OdeSystem(
            states=tuple(self.states),
            inputs=tuple(self.inputs),
            rhs=tuple(rows[n] for n in self.state_names),
            parameters=tuple(syms),
            parameter_values=tuple(float(v) for v in values),
            name=name,
            outputs=outputs,
        )

    # -- JSON -------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The JSON document written by ``symsbl identify --json`` (see *The model file* in the documentation)."""
        return model_to_json(self)

    def save(self, path: str | Path) -> None:
        """Write ``to_json()`` to ``path``, renamed into place (a link's target; a FIFO or device written through)."""
        save_model(self, path)

    @classmethod
    def from_json(cls, doc: dict[str, Any] | str) -> IdentifiedModel:
        """Rebuild a model from ``to_json()`` output (a dict or a JSON string), read as data: term
        texts are parsed by a whitelist grammar, never evaluated."""
        return model_from_json(cls, doc)

    @classmethod
    def load(cls, path: str | Path) -> IdentifiedModel:
        """Read a model saved by :meth:`save` or ``symsbl identify --json``."""
        return load_model(cls, path)


def _degree(term: sp.Expr, name: str) -> float | None:
    """The power ``d`` with ``term(s z) = s^d term(z)`` for every ``s > 0``, ``z`` the symbol ``name`` (0 when the term
    does not use it; None when no power does it), checked numerically at random points for ``s`` = 2 and 1/2
    (sympy's simplification misses ``Max(0, s z) = s Max(0, z)``)."""
    symbols = sorted(term.free_symbols, key=lambda x: x.name)
    names = [x.name for x in symbols]
    if name not in names:
        return 0.0
    k = names.index(name)
    f = sp.lambdify(symbols, term, "numpy")
    rng = np.random.default_rng(0)
    P = rng.uniform(0.5, 2.0, (len(symbols), 32)) * rng.choice([-1.0, 1.0], (len(symbols), 32))
    powers = []
    with np.errstate(all="ignore"):  # points outside the term's domain are left out
        base = np.broadcast_to(np.asarray(f(*P), dtype=float), (32,))
        for s in (2.0, 0.5):
            Q = P.copy()
            Q[k] *= s
            ratio = np.broadcast_to(np.asarray(f(*Q), dtype=float), (32,)) / base
            ratio = ratio[np.isfinite(ratio) & (np.abs(base) > 1e-12)]
            if ratio.size == 0 or np.any(ratio <= 0):
                return None
            powers.append(np.log(ratio) / np.log(s))
    d = np.concatenate(powers)
    return float(np.round(d.mean(), 6)) if np.ptp(d) < 1e-6 else None
