"""The output-error fits of one refinement: one compiled structure, fitted on any subset of its terms.

:class:`Engine` compiles the passes once, for the model extended by the candidate terms; a fit of any
sub-model holds the coefficients it leaves out at zero. So the model, the model with every candidate
and the structure model reduction settles on are fitted by one compiled function, and their
evidences are computed on the same records with the same segmentation.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import sympy as sp

from .._base.rule import complexity
from .._data.residuals import effective_fraction
from .._derivatives.weakform import WeakForm
from .._model import IdentifiedModel
from .noise import innovations
from .problem import Parameterisation, Records, choose_substeps, resolve_outputs
from .reuse import passes_of
from .rows import design_rows, simulated_guess, state_guess
from .sensitivity import FIT_SOURCE, Passes
from .smoothing import sign_jumps, smooth_model, smoothing_widths, width_of
from .solver import LM_STEPS, PHI_STOP, TOL, Iterate, Solution, Warm, _growth, _resegment, _state_scale, fit, horizon
from .structure import free_positions, with_terms

__all__ = ["Engine", "Settings", "residual_fraction", "record_horizon"]


#: Samples whose spectrum sets the first segment length at most (the refinement's default sample budget).
SPECTRUM_SAMPLES = 2**18
#: A fit of a staged structure takes passes of its own coefficients when they and the states are at most this share
#: of the structure's sensitivities (a ten-mass chain's first fit: 89 of its 167 coefficients).
SUBSET_SHARE = 0.75
#: Passes of coefficient subsets an engine keeps (the selection refits a few structures in turn).
SUBSETS_KEPT = 4


@dataclasses.dataclass(frozen=True)
class Settings:
    """How the output-error fits of one refinement run (see :func:`symsbl.refine`)."""

    interpolation: str = "cubic"
    substeps: int | str = "auto"
    smooth: bool = True
    jit: object = "auto"
    growth: int = 8
    min_substeps: int = 1
    noise: object = "white"
    doubts: str = "adapt"


class Engine:
    """The compiled structure (the model and its candidates) and the records of one refinement."""

    def __init__(
        self,
        model: IdentifiedModel,
        records,
        measured,
        settings: Settings,
        candidates: dict,
        guess: np.ndarray | None = None,
    ):
        """``measured``: the channels fitted (names of the model's outputs, or states as they are); ``guess``:
        :func:`state_guess` of ``records`` when the caller has it (else computed)."""
        self.outputs = resolve_outputs(model, measured)
        self.model, self.records, self.settings = model, records, settings
        self.measured = tuple(o.name for o in self.outputs)
        self.full = with_terms(model, candidates)
        self.positions = free_positions(self.full)
        own = set(free_positions(model))
        self.base = np.array([k for k, p in enumerate(self.positions) if p in own], dtype=int)
        self.keys = [complexity(self.full.equations[i].terms[j].sympy) for i, j in self.positions]
        #: ``(state, term)`` of each compiled coefficient, and the position of each such pair: every mapping
        #: between engines and structures goes by these names.
        self.names = [(self.full.equations[i].lhs, self.full.equations[i].terms[j].name) for i, j in self.positions]
        self.index = {name: k for k, name in enumerate(self.names)}
        self.guess = state_guess(model, records, self.outputs) if guess is None else guess
        self.widths = smoothing_widths(model, records, self.guess)
        fitted = smooth_model(self.full, self.widths) if settings.smooth else self.full
        self.param = Parameterisation.of(fitted)
        substeps = settings.substeps
        if substeps == "auto":
            rate = self._sign_rate()
            substeps = max(
                choose_substeps(self.param, records, self.guess, self.param.theta0, rate), settings.min_substeps
            )
            latent = simulated_guess(model, records, self.outputs, self.guess)
            if latent is not None:  # the states no column holds, as the start simulates them, may be stiffer
                parts, rows = latent
                substeps = max(substeps, choose_substeps(self.param, parts, rows, self.param.theta0, rate))
        self.substeps = int(substeps)
        layout = Records.of(fitted, records, self.outputs, settings.interpolation, self.substeps)
        self.passes = passes_of(self.param, layout, jit=settings.jit, max_source=FIT_SOURCE)
        self._subsets: dict[tuple, Passes] = {}
        self.length0 = self._first_length()
        #: The noise model of the fits: "white", an autoregressive order, or "auto" until a fit has chosen one
        #: (every later fit of this engine keeps that order, so that their evidences compare).
        self.noise = settings.noise
        #: The longest segments of every fit (None: whole records), held short where disturbances accumulate.
        self.longest: int | None = None
        #: Nats within which every fit of this engine stops (the solver's default; the model path's looser).
        self.tol = TOL

    def _sign_rate(self) -> float:
        """The largest rate a ``tanh(a / eps)`` standing for ``sign(a)`` adds at ``a = 0``: the stiffness ``K = |coef|
        |J| / eps`` (``J`` half the term's jump there: 1 for ``sign(v)``; largest over the records' rows when it
        depends on the states or inputs) where ``a`` holds the equation's own state (``sign(v)`` in ``v'``: an
        eigenvalue ``-K``), ``sqrt(K)`` where it does not (``sign(x)`` in ``v'`` closes the loop through ``x' = v``:
        eigenvalues ``+-i sqrt(K)``; counted as ``K``, a spurious ``sign(x)`` took 32 substeps where 7 keep RK4
        stable)."""
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
                    stiffness = abs(t.coef) * size / width_of(atom.args[0], self.widths)
                    own = eq.lhs in {str(s) for s in atom.args[0].free_symbols}
                    rate = max(rate, stiffness if own else math.sqrt(stiffness))
        return rate

    def _first_length(self) -> int:
        """About four periods of the highest frequency the measured states carry, at least 64 samples: the
        shortest over the longest record, read in at most four evenly spaced stretches of
        :data:`SPECTRUM_SAMPLES` / 4 samples (a record that sweeps upwards has its highest frequency late)."""
        r = max(self.records, key=lambda tr: tr.n_samples)
        n = SPECTRUM_SAMPLES // 4 if r.n_samples > SPECTRUM_SAMPLES else r.n_samples
        windows = [
            _window(r.t[a : a + n], np.column_stack([r.column(m)[a : a + n] for m in self.measured]))
            for a in np.unique(np.linspace(0, r.n_samples - n, 4).astype(int))
        ]  # 0.5 / f_hi
        return int(max(64, 8 * min(windows)))

    def passes_for(self, active) -> Passes:
        """The passes of a fit of the coefficients ``active``: the engine's own, or for a staged structure (see
        :class:`~symsbl._refine.sensitivity.Passes`) whose fit frees at most :data:`SUBSET_SHARE` of its
        sensitivities, passes carrying only those (a staged pass costs in proportion to the sensitivities it
        carries, and compiles in about a second)."""
        passes = self.passes
        npar, nx = len(self.positions), len(self.model.states)
        active = tuple(sorted(int(k) for k in active))
        if not passes.staged or len(active) + nx > SUBSET_SHARE * (npar + nx):
            return passes
        if active not in self._subsets:
            while len(self._subsets) >= SUBSETS_KEPT:
                self._subsets.pop(next(iter(self._subsets)))
            self._subsets[active] = Passes(
                passes.param, passes.records, passes.jit, passes.max_source, columns=active, staged=True
            )
        return self._subsets[active]

    def fit(
        self,
        active,
        theta0: np.ndarray,
        alpha0: np.ndarray,
        warm: Solution | Warm | None = None,
        longest: int | None = None,
        screen: int | None = None,
    ) -> Solution:
        """Fit the coefficients ``active`` (indices into the compiled structure's), the others held at ``theta0``;
        from the segments and initial states of ``warm`` when given, else by continuation from short segments
        up to ``longest`` samples (default: whole records, or the engine's :attr:`longest`). ``screen``: at most
        this many Levenberg-Marquardt steps after the first pass, at the start's noise precisions and prior
        (where the structure is heading, not its optimum)."""
        if self.longest is not None:
            longest = self.longest if longest is None else min(int(longest), self.longest)
        sol = fit(
            self.passes_for(active),
            theta0,
            alpha0,
            self.guess,
            active=np.asarray(active, dtype=int),
            length0=self.length0,
            growth=self.settings.growth,
            w=None if warm is None else warm.w,
            warm=warm,
            longest=longest,
            noise=self.noise,
            update_noise=screen is None,
            mackay=screen is None,
            max_iter=LM_STEPS if screen is None else int(screen),
            tol=self.tol,
        )
        if self.noise == "auto":
            self.noise = sol.noise.order
        return sol


@np.errstate(over="ignore", invalid="ignore")  # a state error past doubles is an infinite growth
def _window(t: np.ndarray, X: np.ndarray) -> int:
    """The weak form's automatic window on ``(t, X)``, in sample intervals."""
    window = WeakForm().resolve(t, X).window
    assert window is not None  # resolve() always fixes an automatic window from the data
    return window


def record_horizon(engine: Engine, sol: Solution) -> int | None:
    """Samples within which ``sol``'s model amplifies a state error :data:`PHI_STOP`-fold, when that is shorter
    than the longest record (a hypersensitive record); None otherwise. The segments' growth only suggests it (it
    is extrapolated): it is measured over whole records, in one pass."""
    passes, full = engine.passes, int(engine.passes.records.lengths.max())
    reach = horizon(sol.stages)
    if reach is None or reach >= full:
        return None
    whole = _resegment(
        passes, Iterate(sol.theta, sol.X0, passes.segments(sol.starts), sol.w), passes.segment_starts(full)
    )
    blocks = passes.sensitivities(sol.theta, whole.X0, whole.seg, sol.w)
    phi = _growth(blocks.end_S, sol.theta.size, _state_scale(engine.guess, sol.X0))
    return horizon([{"length": full, "growth": phi}]) if phi > PHI_STOP else None


def residual_fraction(engine: Engine, sol: Solution) -> float:
    """``N_eff / N`` of the output-error residual at ``sol`` (of its innovations, with a noise model; the
    smallest over the measured channels; 1 for white residuals), from its autocorrelation
    (:func:`symsbl._data.residuals.effective_fraction`)."""
    passes = engine.passes
    n = passes.records.n_total
    seg = passes.segments(sol.starts)
    with np.errstate(all="ignore"):
        R = passes.records.Y - passes.outputs(sol.theta, sol.X0, seg)
    valid = passes.valid[:n] & np.isfinite(R)
    noise = sol.noise
    if noise.order:  # the innovations: what the noise model leaves of the residual
        ends = np.append(seg.starts[1:], n)
        E = np.full_like(R, np.nan)
        for c in range(R.shape[1]):
            for a, b in zip(seg.starts, ends):
                if b - a > noise.order:
                    E[a + noise.order : b, c] = innovations(np.where(valid[a:b, c], R[a:b, c], np.nan), noise.ar[c])
        R = E
        valid = valid & np.isfinite(R)
    fractions = [effective_fraction(R[valid[:, c], c]) for c in range(R.shape[1]) if valid[:, c].sum() > 8]
    return max(min(fractions, default=1.0), 1e-3)
