"""The output-error fits of one refinement: one compiled structure, fitted on any subset of its terms.

:class:`Engine` compiles the passes once, for the model extended by the candidate terms; a fit of any
sub-model holds the coefficients it leaves out at zero. So the model, the model with every candidate
and the structure model reduction settles on are fitted by one compiled function, and their
evidences are computed on the same records with the same segmentation.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import numpy as np
import sympy as sp

from .._kinematics import estimate_velocity
from .._model import Equation, FitMethod, IdentifiedModel, TermEstimate
from .._selection import complexity
from .._symbolic import sympy_to_casadi
from .._weakform import WeakForm
from .laplace import reduce_model
from .problem import Parameterisation, Records, choose_substeps
from .selection import free_positions, with_terms
from .sensitivity import Passes
from .solver import PHI_STOP, Solution, _growth, _resegment, _state_scale, fit, horizon

__all__ = ["Engine", "Settings", "sign_jumps", "state_guess", "design_rows", "to_model", "stopwatch",
           "residual_fraction", "record_horizon"]


#: Samples whose spectrum sets the first segment length at most (the refinement's default sample budget).
SPECTRUM_SAMPLES = 2**18


@dataclasses.dataclass(frozen=True)
class Settings:
    """How the output-error fits of one refinement run (see :func:`symsbl.refine`)."""

    interpolation: str = "cubic"
    substeps: int | str = "auto"
    smooth: bool = True
    jit: object = "auto"
    growth: int = 8


def _smoothing_widths(model: IdentifiedModel, records) -> dict:
    """Per state, the width ``eps`` of ``tanh(x / eps)`` that stands for ``sign(x)`` while fitting: about 3e-4
    of the state's standard deviation, rounded to a power of two."""
    widths = {}
    for name in model.state_names:
        cols = [r.column(name) for r in records if name in r.state_names]
        scale = float(np.std(np.concatenate(cols))) if cols else 1.0
        # on a grid of powers of two: records of similar scale (folds, windows, bootstrap copies) give the same
        # expressions and so share one compiled function
        widths[name] = 2.0 ** round(math.log2(3e-4 * (scale if scale > 0 else 1.0)))
    return widths


def _width(expr: sp.Expr, widths: dict) -> float:
    names = sorted(str(s) for s in expr.free_symbols)
    return max((widths.get(n, 1.0) for n in names), default=1.0)


@functools.lru_cache(maxsize=1024)
def sign_jumps(expr: sp.Expr) -> tuple[tuple[sp.Expr, sp.Expr], ...]:
    """Each ``sign(a)`` of ``expr`` across which ``expr`` jumps, with half the jump at ``a = 0``.

    ``sign(x) max(0, |x| - g)`` (a clearance) is continuous: it has no jump and needs no smoothing; ``sign(v)``
    jumps by 2, ``x sign(v)`` by ``2 |x|``. An argument that cannot be solved for zero counts as a jump of the
    sign itself. Cached: every engine of a search asks again about the same terms.
    """
    out = []
    for atom in sorted(expr.atoms(sp.sign), key=sp.default_sort_key):
        arg = atom.args[0]
        half = (expr.subs(atom, 1) - expr.subs(atom, -1)) / 2
        if arg.is_Symbol:
            half = half.subs(arg, 0)
        else:
            symbol = min(arg.free_symbols, key=sp.default_sort_key) if arg.free_symbols else None
            roots = sp.solve(arg, symbol) if symbol is not None else []
            half = half.subs(symbol, roots[0]) if roots else sp.Integer(1)
        half = sp.simplify(half)
        if half != 0:
            out.append((atom, half))
    return tuple(out)


def smooth_model(model: IdentifiedModel, widths: dict) -> IdentifiedModel:
    """The model with ``sign(a)`` replaced by ``tanh(a / eps)`` where the term jumps across ``a = 0``: continuous
    in its coefficients when simulated with fixed steps, so Gauss-Newton sees a calibrated curvature. A sign
    whose term is continuous (a clearance's ``sign(x) max(0, |x| - g)``) is kept: smoothing it would only add
    stiffness."""
    symbols = {s.name(): s for s in model.states + model.inputs}

    def smooth(t: TermEstimate) -> TermEstimate:
        jumps = sign_jumps(t.sympy)
        if not jumps:
            return t
        tanh = {atom: sp.tanh(atom.args[0] / sp.Float(_width(atom.args[0], widths))) for atom, _ in jumps}
        return dataclasses.replace(t, expr=sympy_to_casadi(t.sympy.xreplace(tanh), symbols))

    equations = tuple(dataclasses.replace(eq, terms=tuple(smooth(t) for t in eq.terms)) for eq in model.equations)
    return dataclasses.replace(model, equations=equations)


def state_guess(model: IdentifiedModel, records, measured) -> np.ndarray:
    """Every state at every sample of ``records`` laid end to end: measured values (or a column given as a
    guess), velocities from their positions, zeros."""
    position_of = {v: x for x, v in model.kinematics}
    rows = []
    for r in records:
        G = np.zeros((r.n_samples, len(model.states)))
        for k, name in enumerate(model.state_names):
            if name in measured or name in r.state_names:  # a column not measured: a guess only
                G[:, k] = r.column(name)
            elif name in position_of and position_of[name] in measured:
                G[:, k] = estimate_velocity(r.t, r.column(position_of[name]))
        rows.append(G)
    return np.vstack(rows)


def design_rows(model: IdentifiedModel, records, guess: np.ndarray, most: int = 20000) -> np.ndarray:
    """Rows ``(states, inputs)`` of ``guess`` and the records' inputs, evenly thinned to at most ``most``."""
    U = [np.column_stack([r.column(n) for n in model.input_names]) if model.input_names
         else np.zeros((r.n_samples, 0)) for r in records]
    Z = np.column_stack([guess, np.vstack(U)])
    return Z[:: max(1, len(Z) // most)]


class Engine:
    """The compiled structure (the model and its candidates) and the records of one refinement."""

    def __init__(self, model: IdentifiedModel, records, measured, settings: Settings, candidates: dict,
                 guess: np.ndarray | None = None):
        """``guess``: :func:`state_guess` of ``records`` when the caller has it (else computed)."""
        self.model, self.records, self.measured, self.settings = model, records, tuple(measured), settings
        self.full = with_terms(model, candidates)
        self.positions = free_positions(self.full)
        own = set(free_positions(model))
        self.base = np.array([k for k, p in enumerate(self.positions) if p in own], dtype=int)
        self.keys = [complexity(self.full.equations[i].terms[j].sympy) for i, j in self.positions]
        self.widths = _smoothing_widths(model, records)
        self.guess = state_guess(model, records, self.measured) if guess is None else guess
        fitted = smooth_model(self.full, self.widths) if settings.smooth else self.full
        self.param = Parameterisation.of(fitted)
        substeps = settings.substeps
        if substeps == "auto":
            substeps = choose_substeps(self.param, records, self.guess, self.param.theta0, self._sign_rate())
        self.substeps = int(substeps)
        layout = Records.of(fitted, records, self.measured, settings.interpolation, self.substeps)
        self.passes = Passes(self.param, layout, jit=settings.jit)
        self.length0 = self._first_length()

    def _sign_rate(self) -> float:
        """The largest stiffness ``|coef| |J| / eps`` a ``tanh(a / eps)`` standing for ``sign(a)`` adds at ``a = 0``,
        ``J`` half the term's jump there (1 for ``sign(v)``; largest over the records' rows when it depends on
        the states or inputs)."""
        if not self.settings.smooth:
            return 0.0
        rate = 0.0
        names = self.model.state_names + self.model.input_names
        Z = None
        for eq in self.full.equations:
            for t in eq.terms:
                for atom, half in sign_jumps(t.sympy):
                    if half.free_symbols:
                        if Z is None:
                            Z = design_rows(self.model, self.records, self.guess)
                        f = sp.lambdify([sp.Symbol(n) for n in names], half, "numpy")
                        size = float(np.max(np.abs(np.broadcast_to(f(*Z.T), Z.shape[:1]))))
                    else:
                        size = abs(float(half))
                    rate = max(rate, abs(t.coef) * size / _width(atom.args[0], self.widths))
        return rate

    def _first_length(self) -> int:
        """About four periods of the highest frequency the measured states carry, at least 64 samples: the
        shortest over the longest record, read in at most four evenly spaced stretches of
        :data:`SPECTRUM_SAMPLES` / 4 samples (a record that sweeps upwards has its highest frequency late)."""
        r = max(self.records, key=lambda tr: tr.n_samples)
        n = SPECTRUM_SAMPLES // 4 if r.n_samples > SPECTRUM_SAMPLES else r.n_samples
        windows = [WeakForm().resolve(r.t[a:a + n], np.column_stack([r.column(m)[a:a + n] for m in self.measured]))
                   .window for a in np.unique(np.linspace(0, r.n_samples - n, 4).astype(int))]  # 0.5 / f_hi
        return int(max(64, 8 * min(windows)))

    def fit(self, active, theta0: np.ndarray, alpha0: np.ndarray, warm: Solution | None = None,
            longest: int | None = None) -> Solution:
        """Fit the coefficients ``active`` (indices into the compiled structure's), the others held at ``theta0``;
        from the segments and initial states of ``warm`` when given, else by continuation from short segments
        up to ``longest`` samples (default: whole records)."""
        return fit(self.passes, theta0, alpha0, self.guess, active=np.asarray(active, dtype=int),
                   length0=self.length0, growth=self.settings.growth, w=None if warm is None else warm.w, warm=warm,
                   longest=longest)


@np.errstate(over="ignore", invalid="ignore")  # a state error past doubles is an infinite growth
def record_horizon(engine: Engine, sol: Solution) -> int | None:
    """Samples within which ``sol``'s model amplifies a state error :data:`PHI_STOP`-fold, when that is shorter
    than the longest record (a hypersensitive record); None otherwise. The segments' growth only suggests it (it
    is extrapolated): it is measured over whole records, in one pass."""
    passes, full = engine.passes, int(engine.passes.records.lengths.max())
    reach = horizon(sol.stages)
    if reach is None or reach >= full:
        return None
    passes.use_segments(sol.starts)
    X0 = _resegment(passes, sol.theta, sol.X0, passes.segment_starts(full))
    phi = _growth(passes.sensitivities(sol.theta, X0)[3], sol.theta.size, _state_scale(engine.guess, sol.X0))
    passes.use_segments(sol.starts)
    return horizon([{"length": full, "growth": phi}]) if phi > PHI_STOP else None


def residual_fraction(engine: Engine, sol: Solution) -> float:
    """``N_eff / N`` of the output-error residual at ``sol`` (the smallest over the measured channels; 1 for
    white residuals), from its autocorrelation (:func:`symsbl._discrepancy.locate.effective_fraction`)."""
    from .._discrepancy.locate import effective_fraction

    passes = engine.passes
    passes.use_segments(sol.starts)
    n = passes.records.n_total
    with np.errstate(all="ignore"):
        R = passes.records.Y - passes.simulate(sol.theta, sol.X0)[:, list(passes.records.measured)]
    valid = passes.valid[:n] & np.isfinite(R)
    fractions = [effective_fraction(R[valid[:, c], c]) for c in range(R.shape[1]) if valid[:, c].sum() > 8]
    return max(min(fractions, default=1.0), 1e-3)


def to_model(engine: Engine, sol: Solution, info: dict) -> IdentifiedModel:
    """The model of the fitted sub-structure with the output-error posterior; ``metadata["refine"]`` always
    holds the integrator settings (RK4 substeps, input interpolation) it was fitted with, which
    :func:`symsbl.validate_model` re-simulates it with (a Coulomb force of 5 % of the excitation,
    re-simulated with one step per sample instead of the fit's four, strayed 0.35 % from the truth)."""
    fitted = {"substeps": engine.substeps, "interpolation": engine.settings.interpolation}
    info = dict(info, refine={**fitted, **info.get("refine", {})})
    post, active = sol.posterior, list(sol.active)
    where = {engine.positions[k]: n for n, k in enumerate(active)}
    std = post.std
    noise = {m: 1.0 / w for m, w in zip(engine.measured, sol.w)}
    n_samples = int(sum(r.n_samples for r in engine.records))
    equations, free_order = [], []
    for i, eq in enumerate(engine.full.equations):
        if eq.fixed:
            equations.append(eq)
            continue
        kept = [j for j in range(len(eq.terms)) if (i, j) in where or eq.terms[j].fixed]
        idx = [where.get((i, j)) for j in kept]
        free_order += [n for n in idx if n is not None]
        terms = tuple(eq.terms[j] if n is None else
                      TermEstimate(expr=eq.terms[j].expr, coef=float(post.mean[n]), std=float(std[n]),
                                   alpha=float(sol.alpha[active[n]]),
                                   evidence=float(sol.confirmed.get(active[n],
                                                                    -reduce_model(post, sol.alpha[active], [n])[0])),
                                   alternatives=eq.terms[j].alternatives) for j, n in zip(kept, idx))
        equations.append(Equation(eq.lhs, terms, _block(post.covariance, idx), noise.get(eq.lhs, math.nan),
                                  post.log_evidence, n_samples, runners_up=eq.runners_up))
    model = dataclasses.replace(engine.model, equations=tuple(equations), fit=FitMethod.OUTPUT_ERROR,
                                measured=engine.measured, metadata=dict(engine.model.metadata, **info))
    return dataclasses.replace(model, joint_covariance=_joint(model, free_order, post.covariance))


def _block(cov: np.ndarray, idx: list) -> np.ndarray:
    """The covariance of one equation's terms (``None``: a coefficient fixed by convention, zero rows)."""
    out = np.zeros((len(idx), len(idx)))
    free = [p for p, n in enumerate(idx) if n is not None]
    src = [idx[p] for p in free]
    out[np.ix_(free, free)] = cov[np.ix_(src, src)]
    return out


def _joint(model: IdentifiedModel, free_order: list, cov: np.ndarray) -> np.ndarray:
    """The free coefficients' covariance in :meth:`IdentifiedModel.parameters` order (zero for fixed ones)."""
    rows = []
    k = 0
    for eq in model.equations:
        for t in eq.terms:
            free = not eq.fixed and not t.fixed
            rows.append(free_order[k] if free else None)
            k += 1 if free else 0
    n = len(rows)
    out = np.zeros((n, n))
    free = [p for p, r in enumerate(rows) if r is not None]
    src = [rows[p] for p in free]
    out[np.ix_(free, free)] = cov[np.ix_(src, src)]
    return out


def stopwatch():
    """Seconds since the call (a small closure)."""
    start = time.perf_counter()
    return lambda: time.perf_counter() - start
