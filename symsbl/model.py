"""The identified model: posterior per equation, rendered as a symbolic ODE.

An :class:`IdentifiedModel` holds, for each state equation ``x_k' = sum_i beta_i d_i(x, u)``, the
kept candidate terms (CasADi expressions, the single source of truth for names and sympy forms),
their posterior means, standard deviations and covariance, prior precisions, the noise variance
and the log evidence. It renders as

- a readable print with uncertainties, ``x2' = 1.000(0.001) F - 1.0000e4(3) x1 - ...``;
- a sympy system (``to_sympy``, ``to_latex``, ``_repr_latex_``);
- a CasADi :class:`~symsbl.system.OdeSystem` whose coefficients are parameters, ready to simulate;
- JSON (``to_json`` / ``from_json``, ``save`` / ``load``), the format the command line writes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np
import sympy as sp

from .errors import DataError
from .symbolic import casadi_to_sympy, sympy_to_casadi

if TYPE_CHECKING:
    from .system import OdeSystem

__all__ = ["TermEstimate", "Equation", "IdentifiedModel", "format_uncertain"]

JSON_VERSION = 1


@dataclass(frozen=True)
class TermEstimate:
    """Posterior of one kept term of one equation.

    Attributes
    ----------
    expr : casadi.SX
        The candidate term, a scalar expression of the model's states and inputs.
    coef, std : float
        Posterior mean and standard deviation of its coefficient, in the data's units.
    alpha : float
        Optimised prior precision of the coefficient.
    evidence : float
        Log evidence (nats) lost if the term is removed; ``nan`` when unknown.
    alternatives : tuple of str
        Candidates the data cannot tell apart from this term (same fit within the evidence
        tolerance); the simplest of the group is the one kept.
    """

    expr: ca.SX
    coef: float
    std: float
    alpha: float = math.nan
    evidence: float = math.nan
    alternatives: tuple[str, ...] = ()

    @property
    def sympy(self) -> sp.Expr:
        """The term as a sympy expression."""
        return casadi_to_sympy(self.expr)

    @property
    def name(self) -> str:
        """The term's name, its sympy print."""
        return str(self.sympy)

    @property
    def snr(self) -> float:
        """``|coef| / std``, the posterior signal-to-noise ratio of the coefficient."""
        return abs(self.coef) / self.std if self.std > 0 else math.inf


@dataclass(frozen=True)
class Equation:
    """Posterior of one state equation ``lhs' = sum_i coef_i term_i``.

    Attributes
    ----------
    lhs : str
        Name of the state whose derivative this is.
    terms : tuple of TermEstimate
        The kept terms, in library order.
    covariance : ndarray, shape (n_terms, n_terms)
        Posterior covariance of the kept coefficients.
    noise_var : float
        Estimated variance of the equation error (regression-row units).
    log_evidence : float
        Log marginal likelihood of the fitted equation (nats).
    n_rows : int
        Number of regression rows the fit used.
    """

    lhs: str
    terms: tuple[TermEstimate, ...]
    covariance: np.ndarray
    noise_var: float
    log_evidence: float
    n_rows: int = 0

    @property
    def coefs(self) -> np.ndarray:
        """Posterior means, shape ``(n_terms,)``."""
        return np.array([t.coef for t in self.terms])

    @property
    def stds(self) -> np.ndarray:
        """Posterior standard deviations, shape ``(n_terms,)``."""
        return np.array([t.std for t in self.terms])

    @property
    def names(self) -> list[str]:
        """Names of the kept terms."""
        return [t.name for t in self.terms]

    def coef(self, name: str) -> float:
        """Coefficient of the term called ``name`` (0.0 if the term was not kept)."""
        for t in self.terms:
            if t.name == name:
                return t.coef
        return 0.0

    def rhs_sympy(self) -> sp.Expr:
        """Right-hand side with the posterior means as coefficients."""
        return sp.Add(*[sp.Float(t.coef) * t.sympy for t in self.terms])

    def __str__(self) -> str:
        parts = []
        for t in self.terms:
            text = format_uncertain(t.coef, t.std, signed=bool(parts))
            label = _pretty(t.name)
            body = text if label == "1" else f"{text} {label}"
            if t.alternatives:
                body += " (indistinguishable here from " + ", ".join(_pretty(a) for a in t.alternatives) + ")"
            parts.append(body)
        return f"{self.lhs}' = " + (" ".join(parts) if parts else "0")


@dataclass(frozen=True)
class IdentifiedModel:
    """An identified system of ODEs, one :class:`Equation` per state.

    Attributes
    ----------
    states, inputs : tuple of casadi.SX
        Scalar symbols of the states (in equation order) and of the inputs.
    equations : tuple of Equation
        One per state, same order as ``states``.
    metadata : dict
        Free-form provenance (derivative strategy, library size, sample rate ...).

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
    >>> "dot{x_{2}} &= 0.999 F" in model.to_latex(digits=3)
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

    @property
    def state_names(self) -> list[str]:
        """Names of the states."""
        return [s.name() for s in self.states]

    @property
    def input_names(self) -> list[str]:
        """Names of the inputs."""
        return [u.name() for u in self.inputs]

    def equation(self, lhs: str) -> Equation:
        """The equation of the state called ``lhs``."""
        for eq in self.equations:
            if eq.lhs == lhs:
                return eq
        raise KeyError(f"no equation for state {lhs!r}; states are {self.state_names}.")

    def __str__(self) -> str:
        return "\n".join(str(eq) for eq in self.equations)

    # -- symbolic forms -------------------------------------------------------------------
    def to_sympy(self) -> list[sp.Eq]:
        """The system as sympy equations ``Eq(Derivative(x(t), t), rhs)``."""
        t = sp.Symbol("t", real=True)
        out = []
        for eq in self.equations:
            lhs = sp.Derivative(sp.Function(eq.lhs)(t), t)
            out.append(sp.Eq(lhs, eq.rhs_sympy(), evaluate=False))
        return out

    def to_latex(self, digits: int = 4) -> str:
        """LaTeX of the system, coefficients rounded to ``digits`` significant digits."""
        lines = []
        for eq in self.equations:
            rhs = sp.Add(*[sp.Float(t.coef, digits) * t.sympy for t in eq.terms])
            lines.append(rf"\dot{{{sp.latex(sp.Symbol(eq.lhs))}}} &= {sp.latex(rhs)}")
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

    def covariance(self) -> np.ndarray:
        """Block-diagonal posterior covariance of all coefficients, in ``parameters`` order."""
        from scipy.linalg import block_diag

        blocks = [np.atleast_2d(eq.covariance) for eq in self.equations if eq.terms]
        return block_diag(*blocks) if blocks else np.zeros((0, 0))

    def to_system(self, name: str = "identified") -> OdeSystem:
        """The model as a CasADi :class:`~symsbl.system.OdeSystem` with the coefficients as
        parameters (values: the posterior means)."""
        from .system import OdeSystem

        syms, values = self.parameters()
        rhs, k = [], 0
        for eq in self.equations:
            expr = ca.SX(0)
            for t in eq.terms:
                expr = expr + syms[k] * t.expr
                k += 1
            rhs.append(expr)
        return OdeSystem(
            states=tuple(self.states),
            inputs=tuple(self.inputs),
            rhs=tuple(rhs),
            parameters=tuple(syms),
            parameter_values=tuple(float(v) for v in values),
            name=name,
        )

    # -- JSON -------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The JSON document written by ``symsbl identify --json``."""
        equations = []
        for eq in self.equations:
            equations.append(
                {
                    "lhs": eq.lhs,
                    "rhs": str(eq.rhs_sympy()),
                    "terms": [
                        {
                            "term": t.name,
                            "coef": t.coef,
                            "std": t.std,
                            "alpha": _finite_or_none(t.alpha),
                            "evidence": _finite_or_none(t.evidence),
                            "alternatives": list(t.alternatives),
                        }
                        for t in eq.terms
                    ],
                    "noise_std": math.sqrt(eq.noise_var),
                    "log_evidence": eq.log_evidence,
                    "n_rows": eq.n_rows,
                    "covariance": np.asarray(eq.covariance).tolist(),
                }
            )
        return {
            "format": "symsbl-model",
            "version": JSON_VERSION,
            "states": self.state_names,
            "inputs": self.input_names,
            "equations": equations,
            "metadata": _jsonable(self.metadata),
        }

    def save(self, path: str | Path) -> None:
        """Write ``to_json()`` to ``path``."""
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def from_json(cls, doc: dict[str, Any] | str) -> IdentifiedModel:
        """Rebuild a model from ``to_json()`` output (a dict or a JSON string)."""
        if isinstance(doc, str):
            doc = json.loads(doc)
        try:
            state_names, input_names = list(doc["states"]), list(doc.get("inputs", []))
            raw_equations = doc["equations"]
        except (KeyError, TypeError):
            raise DataError(
                "model JSON must have 'states', 'inputs' and 'equations' (as written by "
                f"`symsbl identify --json`); received keys {sorted(doc) if isinstance(doc, dict) else type(doc)}."
            ) from None
        states = tuple(ca.SX.sym(n) for n in state_names)
        inputs = tuple(ca.SX.sym(n) for n in input_names)
        cas = {s.name(): s for s in states + inputs}
        local = {n: sp.Symbol(n, real=True) for n in cas}
        equations = []
        for raw in raw_equations:
            terms = []
            for rt in raw["terms"]:
                try:
                    expr = sp.sympify(rt["term"], locals=local)
                except (sp.SympifyError, SyntaxError, TypeError):
                    raise DataError(f"model JSON: cannot read term {rt['term']!r} of equation {raw['lhs']!r}.") from None
                unknown = {str(s) for s in expr.free_symbols} - set(cas)
                if unknown:
                    raise DataError(
                        f"model JSON: term {rt['term']!r} uses {sorted(unknown)}, which are not among the "
                        f"states {state_names} or inputs {input_names}."
                    )
                terms.append(
                    TermEstimate(
                        expr=sympy_to_casadi(expr, cas),
                        coef=float(rt["coef"]),
                        std=float(rt.get("std", math.nan)),
                        alpha=_none_to_nan(rt.get("alpha")),
                        evidence=_none_to_nan(rt.get("evidence")),
                        alternatives=tuple(rt.get("alternatives", ())),
                    )
                )
            cov = raw.get("covariance")
            cov = np.array(cov, dtype=float).reshape(len(terms), len(terms)) if cov is not None else np.diag([t.std**2 for t in terms])
            equations.append(
                Equation(
                    lhs=raw["lhs"],
                    terms=tuple(terms),
                    covariance=cov,
                    noise_var=float(raw.get("noise_std", math.nan)) ** 2,
                    log_evidence=float(raw.get("log_evidence", math.nan)),
                    n_rows=int(raw.get("n_rows", 0)),
                )
            )
        return cls(states=states, inputs=inputs, equations=tuple(equations), metadata=dict(doc.get("metadata", {})))

    @classmethod
    def load(cls, path: str | Path) -> IdentifiedModel:
        """Read a model saved by :meth:`save` or ``symsbl identify --json``."""
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
        except FileNotFoundError:
            raise DataError(f"model file {str(path)!r} does not exist.") from None
        except json.JSONDecodeError as exc:
            raise DataError(f"model file {str(path)!r} is not valid JSON: {exc}.") from None
        return cls.from_json(doc)


def format_uncertain(value: float, std: float, signed: bool = False) -> str:
    """Format ``value`` with its standard deviation in parentheses, e.g. ``1.000(0.001)``.

    The value is printed to the digit of the standard deviation's leading figure; values of
    magnitude >= 1e4 or < 1e-3 use an exponent, e.g. ``1.0002e4(3)``.

    Parameters
    ----------
    value, std : float
        Mean and standard deviation.
    signed : bool
        Print as a continuation term: ``+ v(s)`` or ``- v(s)``.
    """
    sign = "-" if value < 0 else ""
    v = abs(value)
    if signed:
        sign = "- " if value < 0 else "+ "
    if not np.isfinite(std) or std <= 0:
        return f"{sign}{v:.6g}"
    exp_v = math.floor(math.log10(v)) if v > 0 else 0
    exp_s = math.floor(math.log10(std))
    digits = int(min(max(exp_v - exp_s + 1, 1), 8))
    if v >= 1e4 or (0 < v < 1e-3):
        mant = round(v / 10**exp_v, digits - 1)
        if mant >= 10:  # rounding carried into the next decade
            exp_v += 1
            mant /= 10
        return f"{sign}{mant:.{digits - 1}f}e{exp_v}({_one_figure(std)})"
    decimals = max(-exp_s, 0)
    return f"{sign}{v:.{decimals}f}({_one_figure(std)})"


def _one_figure(std: float) -> str:
    if 1e-3 <= std < 1e4:
        decimals = max(-math.floor(math.log10(std)), 0)
        return f"{std:.{decimals}f}"
    return f"{std:.0e}".replace("e+0", "e").replace("e-0", "e-").replace("e+", "e")


def _pretty(name: str) -> str:
    text = name.replace("**", "^").replace("*", " ")
    while "Abs(" in text:
        i = text.index("Abs(")
        depth, j = 0, i + 3
        for j in range(i + 3, len(text)):
            depth += {"(": 1, ")": -1}.get(text[j], 0)
            if depth == 0:
                break
        text = text[:i] + "|" + text[i + 4 : j] + "|" + text[j + 1 :]
    return text


def _finite_or_none(x: float):
    return float(x) if np.isfinite(x) else None


def _none_to_nan(x) -> float:
    return math.nan if x is None else float(x)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)
