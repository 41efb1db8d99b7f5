"""Validation by re-simulation: run an identified model on held-out data and measure the error.

The identified :class:`~symsbl.IdentifiedModel` is turned into a CasADi
:class:`~symsbl.OdeSystem` and simulated with the measured input of the held-out record
from the initial state that best explains its first stretch. Errors per channel the record holds (a state,
or an output of the model: an acceleration, an algebraic output such as a force):

- NRMSE: RMS of (measured - simulated) divided by the standard deviation of the measured signal;
- fit: ``100 * (1 - NRMSE)`` percent, the usual system-identification "fit".

A model that blows up in simulation is reported with the time it diverged, never as a crash.

Two bands, both from ``validate_model(..., n_band=N)``:

- ``band``, the model's uncertainty: coefficient vectors are drawn from the (block-diagonal)
  Gaussian posterior and simulated; the band is the mean plus or minus three standard deviations
  of the simulated responses. At high sample rates it is narrow.
- ``predictive_band``, where a new *measurement* should fall: the same mean plus or minus three
  times ``sqrt(sd_model**2 + sigma**2)``, with ``sigma`` the white measurement noise of each state
  estimated from the record (:func:`symsbl.noise_levels`). This is the band of Figure 2 of
  Fuentes et al. (2019), which "captures the additive measurement noise"; ``coverage`` reports the
  fraction of measured samples inside it (0.997 for a calibrated Gaussian model).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .._base.checks import choice
from .._base.errors import DataError, DivergenceError, SimulationError, expected
from .._base.progress import Progress
from .._data.trajectory import Trajectory, check_magnitude, noise_levels
from .._derivatives.kinematics import completed_columns
from .._model import IdentifiedModel
from .._model.outputs import latent_of, state_outputs
from .._refine.initial import fitted_start, short_horizons
from .._refine.problem import INTERPOLATIONS
from .._simulation.rk4 import run_rk4_batch
from .._simulation.signals import Sampled
from .._simulation.simulate import resolve_inputs, simulate

__all__ = ["Validation", "validate_model", "nrmse"]


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
        The model's response: its states, then its outputs that are not states (up to the divergence time if it
        diverged).
    nrmse : dict[str, float]
        Per channel of the record the model predicts (a state or an output), RMS error / std of the measured
        signal (``inf`` if the model diverged).
    fit : dict[str, float]
        Per channel, ``100 * (1 - nrmse)`` percent.
    diverged_at : float or None
        Time at which the simulation blew up, None if it completed.
    band : tuple of ndarray or None
        ``(lower, upper)``, each ``(n_samples, n_columns)`` (the columns of ``simulated``): mean -/+ 3 std of the
        Monte Carlo responses over the coefficient posterior; None unless requested.
    status : str
        ``"ok"`` or ``"diverged"``.
    message : str
        Human-readable summary.
    noise_std : dict[str, float] or None
        Per state, the white measurement noise estimated from ``measured`` (with the band).
    band_draws : int
        Monte Carlo draws behind the band; draws whose simulation diverged are left out (and
        said so in ``message``), which narrows the band.
    horizon : float or None
        Seconds within which the model amplifies a state error 10^4-fold on this record, if shorter
        than it (a hypersensitive, chaotic-like record: one simulation of all of it says nothing).
    short_nrmse : dict[str, float] or None
        With ``horizon``: per state, the NRMSE over stretches of a quarter of it (errors grow 10-fold),
        each re-simulated from its own fitted initial state: the validation that works there.
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
    horizon: float | None = None
    short_nrmse: dict | None = None

    def __str__(self) -> str:
        return self.message

    @property
    def predictive_band(self) -> tuple | None:
        """``(lower, upper)`` for a new measurement: the model band widened by the noise.

        Mean -/+ ``3 sqrt(sd_model**2 + noise_std**2)`` per column of ``simulated``, each
        ``(n_samples, n_columns)``;
        None without a band. It assumes white measurement noise (a filtered or differentiated
        state has coloured noise, which the white-noise estimate under-reads) and leaves
        out the noise of the measured initial state the simulation starts from (negligible
        under forcing, lasting in a free decay).
        """
        if self.band is None or self.noise_std is None:
            return None
        lower, upper = self.band
        mean, sd = (upper + lower) / 2, (upper - lower) / 6
        noise = np.array([self.noise_std.get(n, 0.0) for n in self.simulated.state_names])
        half = 3 * np.sqrt(sd**2 + noise**2)
        return mean - half, mean + half

    @property
    def coverage(self) -> dict | None:
        """Per channel, the fraction of measured samples inside :attr:`predictive_band` (None without one)."""
        band = self.predictive_band
        if band is None:
            return None
        names = self.simulated.state_names
        observed = [k for k, n in enumerate(names) if n in self.measured.state_names]
        X = np.column_stack([self.measured.column(names[k]) for k in observed])
        inside = (X >= band[0][:, observed]) & (X <= band[1][:, observed])
        return dict(zip([names[k] for k in observed], map(float, inside.mean(axis=0))))


#: Most Monte Carlo draws a band takes (its 3-sigma edges then known to 0.7 %), and the memory its simulated
#: responses may take (held at once with their deviations: 3 copies of 8 bytes a value).
MAX_BAND_DRAWS, BAND_MEMORY = 10_000, 2 * 2**30


def _input_signal(traj: Trajectory, model: IdentifiedModel, interpolation: str):
    missing = [n for n in model.input_names if n not in traj.input_names]
    if missing:
        raise DataError(
            expected(
                "data",
                f"the model's inputs {list(model.input_names)}",
                f"inputs {list(traj.input_names)} (missing {missing})",
                raw=True,
            )
        )
    if not model.input_names:
        return None
    U = np.column_stack([traj.column(n) for n in model.input_names])
    return Sampled(traj.t, U, kind=interpolation)


def _check(model, data, n_band) -> tuple[str, ...]:
    """The arguments checked; the channels of the record the model predicts (those compared): its states and its
    outputs that are not states."""
    if not isinstance(model, IdentifiedModel):
        raise DataError(expected("model", "an IdentifiedModel", type(model).__name__, raw=True))
    if not isinstance(data, Trajectory):
        raise DataError(expected("data", "a Trajectory", type(data).__name__, raw=True))
    if isinstance(n_band, bool) or not isinstance(n_band, (int, np.integer)) or n_band < 0:
        raise DataError(expected("n_band", "a number of Monte Carlo draws >= 0 (0: no band)", n_band))
    n_cols = len(model.state_names) + sum(o.state is None for o in model.observation)
    most = int(min(MAX_BAND_DRAWS, BAND_MEMORY // (24 * max(data.n_samples, 1) * n_cols)))
    if n_band > most:
        raise DataError(
            expected(
                "n_band",
                f"at most {most} Monte Carlo draws for {data.n_samples} samples of "
                f"{n_cols} channels ({BAND_MEMORY / 2**30:g} GiB held at once)",
                n_band,
                "100 draws give the 3-sigma band to about 7 %, 1000 to about 2 %",
            )
        )
    predicted = list(model.state_names) + [o.name for o in model.observation if o.state is None]
    observed = tuple(n for n in predicted if n in data.state_names)
    here = state_outputs([n for n in model.state_names if n in data.state_names]) + tuple(
        o for o in model.observation if o.state is None and o.name in data.state_names
    )
    unstarted = [n for n in latent_of(model.state_names, here, model.kinematics) if n not in model.latent_names]
    if unstarted or not observed:
        note = (
            " (a member of a position-velocity pair may be missing when another, or its acceleration, is there)"
            if model.kinematics
            else ""
        )
        raise DataError(
            expected(
                "data",
                f"the model's channels {predicted}{note}",
                f"columns {list(data.state_names)} (missing {unstarted or predicted})",
                raw=True,
            )
        )
    bad = [f"{eq.lhs}: {t.name}" for eq in model.equations for t in eq.terms if not np.isfinite(t.coef)]
    if bad:
        raise DataError(expected("model", "finite coefficients", f"non-finite ones for {bad}", raw=True))
    check_magnitude(data)
    return observed


def _initial_state(
    model: IdentifiedModel, data: Trajectory, observed, how: str, interpolation: str, substeps: int
) -> tuple[np.ndarray, int | None]:
    """The start of the re-simulation: the first sample (a member of a kinematic pair the record lacks
    reconstructed from the others, a latent state at its typical fitted value, else zero) or, ``how="fit"``, the
    state that best explains the first stretch of the ``observed`` channels; and the samples in which a state
    error grows 10^4-fold."""
    acceleration = {o.equation: o.name for o in model.observation if o.kind == "acceleration"}
    triples = [(x, v, acceleration.get(v)) for x, v in model.kinematics]
    columns = completed_columns(data, model.state_names, triples)
    rest = _latent_start(model)
    x0 = np.array([columns[n][0] if n in columns else rest.get(n, 0.0) for n in model.state_names])
    if how == "first":
        return x0, None

    length = _fitted(model, "segment_length", lambda v: isinstance(v, int) and v > 0, data.n_samples)
    return fitted_start(
        model, data, observed, x0, interpolation=interpolation, substeps=substeps, length=min(length, 8192)
    )


def _latent_start(model: IdentifiedModel) -> dict:
    """Where each latent state starts when the record says nothing: its typical fitted initial value
    (``metadata["refine"]["latent_start"]``; a value that is not a finite number is ignored), else zero. A level
    under a square root has no derivative at zero: started there, the initial-state fit of a held-out record of
    two tanks failed (11 % error, the record judged hypersensitive), against the noise floor from it."""
    given = _fitted(model, "latent_start", lambda v: isinstance(v, dict), {})
    return {
        n: float(v)
        for n, v in given.items()
        if n in model.state_names and isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }


def _settings(model: IdentifiedModel, interpolation, substeps) -> tuple[str, int]:
    """The input interpolation and RK4 substeps: as given, else the model's refinement's, else cubic and 1."""
    interpolation = interpolation or _fitted(model, "interpolation", lambda v: v in INTERPOLATIONS, "cubic")
    substeps = substeps or _fitted(model, "substeps", lambda v: isinstance(v, int) and 1 <= v <= 64, 1)
    return interpolation, substeps


def _fitted(model: IdentifiedModel, key: str, valid, default):
    """A setting of the model's refinement (``metadata["refine"]``; a model file's metadata is data, so a
    value that is not ``valid`` is ignored)."""
    fitted = model.metadata.get("refine")
    value = fitted.get(key) if isinstance(fitted, dict) else None
    try:
        return value if not isinstance(value, bool) and valid(value) else default
    except TypeError:  # an unhashable value tested for membership
        return default


def validate_model(
    model: IdentifiedModel,
    data: Trajectory,
    *,
    method: str = "auto",
    substeps: int | None = None,
    n_band: int = 0,
    seed: int = 0,
    interpolation: str | None = None,
    initial_state: str = "fit",
) -> Validation:
    """Re-simulate ``model`` on ``data``'s input from its first state; report the error.

    Parameters
    ----------
    model : IdentifiedModel
    data : Trajectory
        Held-out record with the model's states and inputs (matched by name).
    method : {"auto", "cvodes", "rk4"}
        Integrator, see :func:`symsbl.simulate`. ``"auto"`` uses RK4 with the input held
        linear between samples when the record has inputs (CVODES would restart at every input
        sample) and the simulator's own choice for free decay.
    substeps : int, optional
        RK4 steps per sample (default: the model's refinement's, else 1).
    n_band : int
        Number of Monte Carlo draws from the coefficient posterior for the 3-sigma bands
        (0: no band); see :attr:`Validation.band` and :attr:`Validation.predictive_band`.
    seed : int
        Seed of the Monte Carlo draws.
    interpolation : {"cubic", "linear", "periodic"}, optional
        How the measured input runs between samples (default: the model's refinement's, else a
        cubic spline, see :class:`symsbl.Sampled`).
    initial_state : {"fit", "first"}
        Start from the state that best explains the record's first stretch (default; the length the
        model's output-error refinement stopped at, at most 8192 samples): a noisy first sample
        would otherwise shift a limit cycle's phase for good, and an unmeasured state has no sample.
        ``"first"`` starts from the first sample (an unmeasured velocity estimated from its position).

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
    observed = _check(model, data, n_band)
    interpolation, substeps = _settings(model, interpolation, substeps)
    system = model.to_system()
    signal = _input_signal(data, model, interpolation)
    if method == "auto" and signal is not None:
        # A measured input is known at its samples only; interpolated between them it has a
        # kink or a jump in curvature at every sample, which makes CVODES cut its step at each one
        # (measured: 0.9 s for 1 s at 32768 Hz, against 0.085 s for RK4, whose compiled step is
        # also shared by every Monte Carlo draw).
        method = "rk4"
    choice("initial_state", initial_state, ("fit", "first"), error=DataError)
    x0, reach = _initial_state(model, data, observed, initial_state, interpolation, substeps)
    kw = dict(inputs=signal, x0=x0, method=method, substeps=substeps, on_divergence="truncate")
    try:
        sim = simulate(system, data.t, **kw)
    except DivergenceError as exc:  # within the first step: the first two samples stand for the response
        first = np.concatenate([x0, system.evaluate_outputs(x0[None, :], _inputs_at(data, model)[:1])[0]])
        sim = Trajectory(
            data.t[:2],
            np.vstack([first, first]),
            None,
            model.state_names + system.output_names,
            diverged_at=exc.diverged_at,
        )
    n = sim.n_samples
    diverged = getattr(sim, "diverged_at", None)
    if diverged is not None or n < data.n_samples:
        at = diverged if diverged is not None else float(data.t[n])
        return Validation(
            data,
            sim,
            {s: math.inf for s in observed},
            {s: -math.inf for s in observed},
            at,
            None,
            "diverged",
            f"the identified model diverged in simulation at t = {at:.6g} s "
            f"(of {data.t[-1] - data.t[0]:.6g} s); it is unstable on this input.",
        )
    X = np.column_stack([data.column(n) for n in observed])
    err = dict(zip(observed, map(float, nrmse(X, np.column_stack([sim.column(n) for n in observed])))))
    fit = {k: 100.0 * (1.0 - v) for k, v in err.items()}
    band, draws = _band(model, system, data, kw, n_band, seed) if n_band else (None, 0)
    noise = None
    if band is not None:
        levels = noise_levels(data)
        noise = {s: levels[s] for s in observed}
    result = Validation(data, sim, err, fit, None, band, "ok", "", noise, draws)
    if reach is not None and reach < data.n_samples:  # hypersensitive here: judged over short horizons
        X = short_horizons(
            model, data, observed, interpolation=interpolation, substeps=substeps, length=max(reach // 4, 16)
        )
        columns = np.column_stack([X, system.evaluate_outputs(X, _inputs_at(data, model))])
        names = model.state_names + system.output_names
        pieces = columns[:, [names.index(n) for n in observed]]
        X = np.column_stack([data.column(n) for n in observed])
        result = dataclasses.replace(
            result, horizon=float(reach * data.dt), short_nrmse=dict(zip(observed, map(float, nrmse(X, pieces))))
        )
    return dataclasses.replace(result, message=_message(result, n_band))


def _message(result, n_band: int) -> str:
    coverage = result.coverage or {}
    lines = [
        f"{k}: NRMSE {100 * v:.3g} %, fit {result.fit[k]:.2f} %"
        + (f", {100 * coverage[k]:.1f} % of samples inside the 3-sigma predictive band" if k in coverage else "")
        for k, v in result.nrmse.items()
    ]
    if result.horizon is not None:
        lines.append(
            f"hypersensitive record (chaotic-like): the model amplifies a state error 10^4-fold within "
            f"{result.horizon:.3g} s, so one simulation of the whole record says nothing of it; over "
            f"stretches of {result.horizon / 4:.3g} s, each from its fitted initial state: "
            + ", ".join(f"{k}: NRMSE {100 * v:.3g} %" for k, v in result.short_nrmse.items())
        )
    if n_band and result.band_draws < n_band:
        lines.append(
            f"the band uses {result.band_draws} of {n_band} posterior draws; the others diverged in "
            "simulation" + ("" if result.band is not None else ", too many to draw a band")
        )
    return "\n".join(lines)


def _inputs_at(data: Trajectory, model: IdentifiedModel) -> np.ndarray:
    """The model's inputs at the record's samples, ``(n_samples, n_inputs)``."""
    if not model.input_names:
        return np.zeros((data.n_samples, 0))
    return np.column_stack([data.column(n) for n in model.input_names])


def _band(model, system, data, kw, n_band, seed):
    draws = _draws(model, n_band, seed)
    n_cols = system.n_states + len(system.outputs)
    if kw["method"] == "rk4":  # every draw in one compiled call per chunk: (n_samples, n_draws, n_states)
        signals = resolve_inputs(system, data.t, kw["inputs"])
        states, finite = run_rk4_batch(system, data.t, signals, kw["x0"], draws, substeps=kw["substeps"])
        runs = states[:, finite] if not finite.all() else states
        if system.outputs and runs.shape[1]:  # each draw's outputs at its own coefficients
            U = _inputs_at(data, model)
            kept = draws[finite]
            runs = np.concatenate(
                [
                    runs,
                    np.stack([system.evaluate_outputs(runs[:, d], U, kept[d]) for d in range(runs.shape[1])], axis=1),
                ],
                axis=2,
            )
    else:
        loop = _band_loop(system, data, kw, draws)
        runs = np.stack(loop, axis=1) if loop else np.empty((data.n_samples, 0, n_cols))
    n = runs.shape[1] if runs.ndim == 3 else 0
    if n < 2:
        return None, n
    mu = runs.sum(axis=1) / n  # numpy's mean/std over the middle axis took 3x longer than the simulation
    dev = runs - mu[:, None]
    sd = np.sqrt(np.einsum("ndk,ndk->nk", dev, dev) / (n - 1))
    return (mu - 3 * sd, mu + 3 * sd), n


def _draws(model: IdentifiedModel, n_band: int, seed) -> np.ndarray:
    """Seeded posterior draws of the coefficients; round-off may leave a joint Laplace covariance slightly
    indefinite, so the square root clips negative eigenvalues."""
    _, mean = model.parameters()
    cov = model.covariance()
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    root = v * np.sqrt(np.clip(w, 0.0, None))
    return mean + np.random.default_rng(seed).standard_normal((n_band, mean.size)) @ root.T


def _band_loop(system, data, kw, draws) -> list:
    """One simulation per draw (CVODES, for records without inputs)."""
    runs = []
    with Progress("predictive band (Monte Carlo)", total=len(draws), unit="draws") as bar:
        for theta in draws:
            sys_k = dataclasses.replace(system, parameter_values=tuple(float(v) for v in theta))
            try:
                sim = simulate(sys_k, data.t, **kw)
            except SimulationError:
                sim = None
            if sim is not None and sim.n_samples == data.n_samples and sim.diverged_at is None:
                runs.append(sim.states)
            bar.update()
    return runs
