"""Validation by re-simulation: run an identified model on held-out data and measure the error.

The identified :class:`~symsbl.model.IdentifiedModel` is turned into a CasADi
:class:`~symsbl.system.OdeSystem` and simulated with the measured input of the held-out record
from its first measured state. Errors per state:

- NRMSE: RMS of (measured - simulated) divided by the standard deviation of the measured signal;
- fit: ``100 * (1 - NRMSE)`` percent, the usual system-identification "fit".

A model that blows up in simulation is reported with the time it diverged, never as a crash.

Two bands, both from ``validate_model(..., n_band=N)``:

- ``band``, the model's uncertainty: coefficient vectors are drawn from the (block-diagonal)
  Gaussian posterior and simulated; the band is the mean plus or minus three standard deviations
  of the simulated responses. At high sample rates it is narrow.
- ``predictive_band``, where a new *measurement* should fall: the same mean plus or minus three
  times ``sqrt(sd_model**2 + sigma**2)``, with ``sigma`` the white measurement noise of each state
  estimated from the record (:func:`symsbl.data.noise_levels`). This is the band of Figure 2 of
  Fuentes et al. (2019), which "captures the additive measurement noise"; ``coverage`` reports the
  fraction of measured samples inside it (0.997 for a calibrated Gaussian model).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .data import Trajectory, noise_levels
from .errors import DataError, SimulationError
from .model import IdentifiedModel
from .progress import Progress
from .signals import Sampled
from .simulate import simulate

__all__ = ["Validation", "validate_model", "nrmse", "TruthComparison", "compare_to_truth"]


def nrmse(measured: np.ndarray, simulated: np.ndarray) -> np.ndarray:
    """RMS error divided by the standard deviation of ``measured``, per column.

    Parameters
    ----------
    measured, simulated : ndarray, shape (n_samples,) or (n_samples, n_channels)

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> float(symsbl.nrmse(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 4.0])))
    0.7071067811865475
    """
    measured = np.asarray(measured, dtype=float)
    simulated = np.asarray(simulated, dtype=float)
    err = np.sqrt(np.mean((measured - simulated) ** 2, axis=0))
    scale = np.std(measured, axis=0)
    return err / np.where(scale > 0, scale, 1.0)


@dataclass(frozen=True)
class Validation:
    """Result of re-simulating a model on a record.

    Attributes
    ----------
    measured : Trajectory
        The record the model was run on.
    simulated : Trajectory
        The model's response (up to the divergence time if it diverged).
    nrmse : dict[str, float]
        Per state, RMS error / std of the measured signal (``inf`` if the model diverged).
    fit : dict[str, float]
        Per state, ``100 * (1 - nrmse)`` percent.
    diverged_at : float or None
        Time at which the simulation blew up, None if it completed.
    band : tuple of ndarray or None
        ``(lower, upper)``, each ``(n_samples, n_states)``: mean -/+ 3 std of the Monte Carlo
        responses over the coefficient posterior; None unless requested.
    status : str
        ``"ok"`` or ``"diverged"``.
    message : str
        Human-readable summary.
    noise_std : dict[str, float] or None
        Per state, the white measurement noise estimated from ``measured`` (with the band).
    band_draws : int
        Monte Carlo draws behind the band; draws whose simulation diverged are left out (and
        said so in ``message``), which narrows the band.
    """

    measured: Trajectory
    simulated: Trajectory
    nrmse: dict
    fit: dict
    diverged_at: float | None
    band: tuple | None
    status: str
    message: str
    noise_std: dict | None = None
    band_draws: int = 0

    def __str__(self) -> str:
        return self.message

    @property
    def predictive_band(self) -> tuple | None:
        """``(lower, upper)`` for a new measurement: the model band widened by the noise.

        Mean -/+ ``3 sqrt(sd_model**2 + noise_std**2)`` per state, each ``(n_samples, n_states)``;
        None without a band. It assumes white measurement noise (a filtered or differentiated
        state has coloured noise, which the third-difference estimate under-reads) and leaves
        out the noise of the measured initial state the simulation starts from (negligible
        under forcing, lasting in a free decay).
        """
        if self.band is None or self.noise_std is None:
            return None
        lower, upper = self.band
        mean, sd = (upper + lower) / 2, (upper - lower) / 6
        noise = np.array([self.noise_std[n] for n in self.simulated.state_names])
        half = 3 * np.sqrt(sd**2 + noise**2)
        return mean - half, mean + half

    @property
    def coverage(self) -> dict | None:
        """Per state, the fraction of measured samples inside :attr:`predictive_band` (None without one)."""
        band = self.predictive_band
        if band is None:
            return None
        X = np.column_stack([self.measured.column(n) for n in self.simulated.state_names])
        inside = (X >= band[0]) & (X <= band[1])
        return dict(zip(self.simulated.state_names, map(float, inside.mean(axis=0))))


def _input_signal(traj: Trajectory, model: IdentifiedModel):
    missing = [n for n in model.input_names if n not in traj.input_names]
    if missing:
        raise DataError(
            f"the model has inputs {model.input_names} but the data has inputs "
            f"{list(traj.input_names)}; missing {missing}."
        )
    if not model.input_names:
        return None
    U = np.column_stack([traj.column(n) for n in model.input_names])
    return Sampled(traj.t, U)


def validate_model(
    model: IdentifiedModel,
    data: Trajectory,
    *,
    method: str = "auto",
    substeps: int = 1,
    n_band: int = 0,
    seed: int = 0,
) -> Validation:
    """Re-simulate ``model`` on ``data``'s input from its first state; report the error.

    Parameters
    ----------
    model : IdentifiedModel
    data : Trajectory
        Held-out record with the model's states and inputs (matched by name).
    method : {"auto", "cvodes", "rk4"}
        Integrator, see :func:`symsbl.simulate.simulate`. ``"auto"`` uses RK4 with the input held
        linear between samples when the record has inputs (CVODES would restart at every input
        sample) and the simulator's own choice for free decay.
    substeps : int
        RK4 steps per sample.
    n_band : int
        Number of Monte Carlo draws from the coefficient posterior for the 3-sigma bands
        (0: no band); see :attr:`Validation.band` and :attr:`Validation.predictive_band`.
    seed : int
        Seed of the Monte Carlo draws.

    Returns
    -------
    Validation

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify(train, library)
    >>> test = symsbl.simulate(duffing, symsbl.time_grid(0.5, 8192),
    ...                        inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1))
    >>> check = symsbl.validate_model(model, test.with_noise(0.004, seed=2), n_band=10)
    >>> check.status, max(check.nrmse.values()) < 0.01
    ('ok', True)
    >>> lower, upper = check.predictive_band   # where new measurements should fall
    >>> lower.shape
    (4097, 2)
    >>> all(share > 0.98 for share in check.coverage.values())   # 0.997 if calibrated
    True
    """
    if not isinstance(data, Trajectory):
        raise DataError(f"data must be a Trajectory; received {type(data).__name__}.")
    if isinstance(n_band, bool) or not isinstance(n_band, (int, np.integer)) or n_band < 0:
        raise DataError(f"n_band: expected a number of Monte Carlo draws >= 0 (0: no band); received {n_band!r}.")
    missing = [n for n in model.state_names if n not in data.state_names]
    if missing:
        raise DataError(
            f"the model has states {model.state_names} but the data has states "
            f"{list(data.state_names)}; missing {missing}."
        )
    system = model.to_system()
    signal = _input_signal(data, model)
    if method == "auto" and signal is not None:
        # A measured input is known at its samples only; held linear between them it has a
        # kink at every sample, which makes CVODES cut its step at each one (measured: 0.9 s
        # for 1 s at 32768 Hz, against 0.085 s for RK4 with the same linear hold, whose compiled
        # step is also reused across the Monte Carlo draws).
        method = "rk4"
    X = np.column_stack([data.column(n) for n in model.state_names])
    kw = dict(inputs=signal, x0=X[0], method=method, substeps=substeps, on_divergence="truncate")
    sim = simulate(system, data.t, **kw)
    n = sim.n_samples
    diverged = getattr(sim, "diverged_at", None)
    if diverged is not None or n < data.n_samples:
        err = {s: math.inf for s in model.state_names}
        fit = {s: -math.inf for s in model.state_names}
        at = diverged if diverged is not None else float(data.t[n])
        return Validation(
            data, sim, err, fit, at, None, "diverged",
            f"the identified model diverged in simulation at t = {at:.6g} s "
            f"(of {data.t[-1] - data.t[0]:.6g} s); it is unstable on this input.",
        )
    errs = nrmse(X, sim.states)
    err = dict(zip(model.state_names, map(float, errs)))
    fit = {k: 100.0 * (1.0 - v) for k, v in err.items()}
    band, draws = _band(model, system, data, kw, n_band, seed) if n_band else (None, 0)
    noise = None
    if band is not None:
        levels = noise_levels(data)
        noise = {s: levels[s] for s in model.state_names}
    result = Validation(data, sim, err, fit, None, band, "ok", "", noise, draws)
    coverage = result.coverage or {}
    lines = [f"{k}: NRMSE {100 * v:.3g} %, fit {fit[k]:.2f} %"
             + (f", {100 * coverage[k]:.1f} % of samples inside the 3-sigma predictive band" if k in coverage else "")
             for k, v in err.items()]
    if n_band and draws < n_band:
        lines.append(f"the band uses {draws} of {n_band} posterior draws; the others diverged in simulation"
                     + ("" if band is not None else ", too many to draw a band"))
    return dataclasses.replace(result, message="\n".join(lines))


def _band(model, system, data, kw, n_band, seed):
    _, mean = model.parameters()
    cov = model.covariance()
    rng = np.random.default_rng(seed)
    draws = rng.multivariate_normal(mean, cov, size=n_band, method="eigh")
    runs = []
    with Progress("predictive band (Monte Carlo)", total=n_band, unit="draws") as bar:
        for theta in draws:
            sys_k = dataclasses.replace(system, parameter_values=tuple(float(v) for v in theta))
            try:
                sim = simulate(sys_k, data.t, **kw)
            except SimulationError:
                sim = None
            if sim is not None and sim.n_samples == data.n_samples and sim.diverged_at is None:
                runs.append(sim.states)
            bar.update()
    if len(runs) < 2:
        return None, len(runs)
    runs = np.array(runs)
    mu, sd = runs.mean(axis=0), runs.std(axis=0, ddof=1)
    return (mu - 3 * sd, mu + 3 * sd), len(runs)


@dataclass(frozen=True)
class TruthComparison:
    """How an identified model compares with the system that generated the data.

    Attributes
    ----------
    exact_support : bool
        Every equation has exactly the true terms: none missing, none spurious.
    missing, spurious : dict[str, list[str]]
        Per state, true terms not found and found terms not in the truth.
    relative_error : dict[str, dict[str, float]]
        Per state and true term, ``|coef - true| / |true|`` (``inf`` if missing).
    variance_share : dict[str, dict[str, float]]
        Per state and true term, ``var(coef * term)`` divided by the sum of these variances over
        the equation's true terms, on the given data (to judge small terms such as Coulomb
        friction); 1.0 when no data is given.
    """

    exact_support: bool
    missing: dict
    spurious: dict
    relative_error: dict
    variance_share: dict

    def max_error(self, min_share: float = 0.0) -> float:
        """Largest relative coefficient error over terms with at least ``min_share`` of their
        equation's variance."""
        errs = [
            e
            for state, terms in self.relative_error.items()
            for name, e in terms.items()
            if self.variance_share[state][name] >= min_share
        ]
        return max(errs) if errs else 0.0


def _true_terms(system) -> list[dict]:
    import sympy as sp

    out = []
    for rhs in system.to_sympy():
        terms = {}
        for part in sp.Add.make_args(sp.expand(rhs.rhs)):
            coef, term = part.as_coeff_Mul()
            terms[str(term)] = terms.get(str(term), 0.0) + float(coef)
        out.append(terms)
    return out


def compare_to_truth(model: IdentifiedModel, system, data: Trajectory | None = None) -> TruthComparison:
    """Compare ``model`` term by term with the true ``system`` (an OdeSystem).

    Terms are matched by their canonical sympy form, so ``Abs(x2)*x3*Abs(x3)`` in the truth
    matches the library term of the same function. A found term that the truth does not
    contain but that is reported indistinguishable from a true term (e.g. ``tan(x1)`` for
    ``x1``) still counts as spurious: parsimony should have kept the true one.

    Parameters
    ----------
    model : IdentifiedModel
    system : OdeSystem
        The system that generated the data.
    data : Trajectory, optional
        Used to compute each true term's variance share.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify(train, library)
    >>> truth = symsbl.compare_to_truth(model, duffing, train)
    >>> truth.exact_support, truth.max_error() < 0.005
    (True, True)
    """
    from .library import Library

    truth = _true_terms(system)
    missing, spurious, rel, share = {}, {}, {}, {}
    for eq, true in zip(model.equations, truth):
        found = {t.name: t.coef for t in eq.terms}
        missing[eq.lhs] = sorted(set(true) - set(found))
        spurious[eq.lhs] = sorted(set(found) - set(true))
        rel[eq.lhs] = {n: abs(found.get(n, math.inf) - c) / abs(c) if n in found else math.inf for n, c in true.items()}
        share[eq.lhs] = {n: 1.0 for n in true}
        if data is not None and true:
            variables = list(system.states) + list(system.inputs)
            lib = Library([t for t in _sympy_terms(true)], variables)
            from .evaluator import Evaluator

            Z = np.column_stack([data.column(v.name()) for v in variables])
            D = Evaluator(lib, jit=False).evaluate(Z)
            contrib = {n: np.var(D[:, lib.index(n)] * c) if n in lib else 0.0 for n, c in true.items()}
            total = sum(contrib.values()) or 1.0
            share[eq.lhs] = {n: float(v / total) for n, v in contrib.items()}
    exact = not any(missing.values()) and not any(spurious.values())
    return TruthComparison(exact, missing, spurious, rel, share)


def _sympy_terms(true: dict):
    import sympy as sp

    names = set()
    for n in true:
        names |= {str(s) for s in sp.sympify(n).free_symbols}
    local = {n: sp.Symbol(n, real=True) for n in names}
    return [sp.sympify(n, locals=local) for n in true]
