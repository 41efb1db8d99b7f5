"""Figures of an identified model (optional extra: ``pip install symsbl[plot]``).

:func:`figure2` draws the three panels of Figure 2 of Fuentes et al. (2019) for one model:
the measured phase portrait, the measured response against the re-simulated one with its
3-sigma predictive band, and the identified coefficients of one equation with their prior and
posterior variances. :func:`coefficient_uncertainty` shows every kept coefficient with its
3-sigma posterior interval relative to its own size. :func:`discrepancy_figure` shows what the discrepancy
workflow found: the held-out response before and after, where in the phase plane the model
disagrees, and the evidence that named the missing effect.

Every function returns a :class:`matplotlib.figure.Figure` built with the object API, so no
window opens and no global pyplot state is touched: save it with ``fig.savefig(path)``, or let
Jupyter display it.

References
----------
R. Fuentes, N. Dervilis, K. Worden, E. J. Cross, "Efficient parameter identification and model
selection in nonlinear dynamical systems via sparse Bayesian learning", J. Phys.: Conf. Ser.
1264 (2019) 012050, Sec. 3 and Figure 2.
"""

from __future__ import annotations

import numpy as np

from .data import Trajectory
from .errors import DataError, MissingExtraError
from .model import Equation, IdentifiedModel, _pretty, format_uncertain
from .validate import Validation, validate_model

__all__ = ["figure2", "coefficient_uncertainty", "discrepancy_figure", "term_label", "forcing_window"]

#: Colours of the measured data, the model and its band (colour-blind safe pair).
_MEASURED = "0.2"
_MODEL = "#d55e00"
_BAND = "#e69f00"
_PRIOR = "#0072b2"
_POSTERIOR = "#009e73"


def _figure(**kwargs):
    """A new :class:`matplotlib.figure.Figure`, or an ImportError that says how to install it."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingExtraError(
            "symsbl's figures need matplotlib, which is not installed; install it with "
            "`pip install symsbl[plot]` (or `pip install matplotlib`)."
        ) from exc
    return Figure(**kwargs)


def term_label(name: str) -> str:
    """Readable label of a term name: ``"x1**2*Abs(x2)"`` -> ``"x1^2 |x2|"``."""
    return _pretty(name)


def _equation_for(model: IdentifiedModel, state: str | None) -> Equation:
    if not model.equations:
        raise DataError("the model has no equations to plot.")
    if state is None:
        # The equation that carries the nonlinearity: most nonlinear terms (x3' of Bouc-Wen, as
        # in the paper's Figure 2e), then most terms; ties go to the later state (x2' rather
        # than the kinematic x1' = x2).
        def weight(eq):
            return sum(not (t.sympy.is_Symbol or t.sympy.is_Number) for t in eq.terms), len(eq.terms)

        return max(reversed(model.equations), key=weight)
    try:
        return model.equation(state)
    except KeyError:
        raise DataError(f"state must be one of the model's states {model.state_names}; received {state!r}.") from None


def forcing_window(data: Trajectory, cycles: float = 1.0, *, threshold: float = 0.1) -> tuple[float, float]:
    """The last ``cycles`` periods of the slowest significant component of the forcing.

    The spectrum of the first input (of the first state if there is none) is computed; the
    lowest frequency whose amplitude exceeds ``threshold`` times the peak sets the period. For
    the paper's 10 Hz sine this is one 0.1 s cycle; for a 2-30 Hz multisine, 0.5 s.

    Parameters
    ----------
    data : Trajectory
    cycles : float
        Number of periods to show.
    threshold : float
        Fraction of the spectral peak above which a frequency counts as significant.

    Returns
    -------
    (t_start, t_stop) : tuple of float
        Seconds, within ``data.t``.
    """
    signal = data.inputs[:, 0] if data.inputs.shape[1] else data.states[:, 0]
    spectrum = np.abs(np.fft.rfft(signal - signal.mean()))
    freqs = np.fft.rfftfreq(signal.size, data.dt)
    t0, t1 = float(data.t[0]), float(data.t[-1])
    if spectrum.size < 2 or spectrum[1:].max() <= 0:
        return t0, t1
    significant = np.flatnonzero(spectrum[1:] >= threshold * spectrum[1:].max()) + 1
    span = cycles / freqs[significant[0]]
    return max(t0, t1 - span), t1


def _phase_portrait(ax, data: Trajectory) -> None:
    x = data.states[:, 0]
    if data.states.shape[1] >= 2:
        y, ylabel = data.states[:, 1], data.state_names[1]
    else:
        y, ylabel = np.gradient(x, data.dt), f"d{data.state_names[0]}/dt (finite difference)"
    ax.plot(x, y, color=_MEASURED, lw=0.6)
    ax.ticklabel_format(style="sci", scilimits=(-2, 3))
    ax.set_xlabel(data.state_names[0])
    ax.set_ylabel(ylabel)
    ax.set_title("(a) measured phase portrait")


def _response(ax, model: IdentifiedModel, validation: Validation, state: str, window) -> None:
    measured, simulated = validation.measured, validation.simulated
    t0, t1 = window
    keep = (measured.t >= t0) & (measured.t <= t1)
    ax.plot(measured.t[keep], measured.column(state)[keep], color=_MEASURED, lw=1.0, label="measured")
    sim_keep = (simulated.t >= t0) & (simulated.t <= t1)
    if sim_keep.any():
        ax.plot(simulated.t[sim_keep], simulated.column(state)[sim_keep], color=_MODEL, lw=1.0, ls="--",
                label="identified model")
    band, label = validation.predictive_band, r"3$\sigma$ predictive band"
    if band is None:
        band, label = validation.band, r"3$\sigma$ band (coefficients)"
    if band is not None:
        k = model.state_names.index(state)
        lower, upper = band[0][:, k], band[1][:, k]
        ax.fill_between(measured.t[keep], lower[keep], upper[keep], color=_BAND, alpha=0.35, lw=0, label=label)
    title = f"(b) {state}: measured and re-simulated"
    if validation.status != "ok":
        title += f" (diverged at t = {validation.diverged_at:.3g} s)"
    else:
        title += f", NRMSE {100 * validation.nrmse[state]:.2g} %"
    ax.set_title(title)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(state)
    ax.set_xlim(t0, t1)
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.25 * (high - low))  # room for the legend above the data
    ax.legend(loc="upper center", ncols=3, fontsize="small", frameon=False)


def _coefficients(ax, equation: Equation) -> None:
    terms = equation.terms
    pos = np.arange(len(terms))
    ax.bar(pos, np.abs(equation.coefs), color="0.55", width=0.6, label=r"$|\beta|$")
    ax.set_yscale("log")
    ax.set_xticks(pos, [term_label(t.name) for t in terms], rotation=30, ha="right")
    ax.set_ylabel(r"$|\beta|$ (posterior mean)")
    ax.set_title(f"(c) identified terms of {equation.lhs}'")
    right = ax.twinx()
    prior = np.array([1.0 / t.alpha if t.alpha > 0 else np.nan for t in terms])
    posterior = equation.stds**2
    right.plot(pos, prior, "o", color=_PRIOR, label=r"prior variance $1/\alpha$")
    right.plot(pos, posterior, "s", mfc="none", color=_POSTERIOR, label=r"posterior variance $\sigma^2$")
    right.set_yscale("log")
    right.set_ylabel("variance")
    for axis in (ax, right):
        _headroom(axis, 0.35)
    low, high = ax.get_ylim()
    ax.set_ylim(min(low, np.abs(equation.coefs).min() / 10), high)  # the smallest bar stays visible
    handles = ax.get_legend_handles_labels()
    more = right.get_legend_handles_labels()
    ax.legend(handles[0] + more[0], handles[1] + more[1], loc="upper left", fontsize="small")


def _headroom(ax, fraction: float) -> None:
    """Raise the top of a log axis so the data fill the lower ``1 - fraction`` of it."""
    low, high = (np.log10(v) for v in ax.get_ylim())
    ax.set_ylim(10**low, 10 ** (high + fraction / (1 - fraction) * (high - low)))


def figure2(
    model: IdentifiedModel,
    validation: Validation,
    *,
    state: str | None = None,
    data: Trajectory | None = None,
    window: tuple[float, float] | None = None,
    cycles: float = 1.0,
):
    """Figure 2 of Fuentes et al. (2019) for one identified model.

    Three panels side by side:

    (a) the phase portrait (first state against the second) of the measured data;
    (b) the measured response of ``state`` against the model's re-simulation, with the
        3-sigma predictive band when it was computed (``validate_model(..., n_band=N)``): the
        Monte Carlo spread of the coefficient posterior widened by the measurement noise,
        :attr:`~symsbl.validate.Validation.predictive_band`, where new measurements should fall;
        over a window of the record;
    (c) the absolute identified coefficients of ``state``'s equation (log scale), one bar per
        kept term, with the prior variance ``1 / alpha`` and posterior variance ``std**2`` on a
        second log axis.

    Parameters
    ----------
    model : IdentifiedModel
    validation : Validation
        The model re-simulated on a record, from :func:`symsbl.validate_model`.
    state : str, optional
        State whose response and equation are shown. Default: the equation that carries the
        nonlinearity, i.e. with the most terms that are neither a bare variable nor a constant,
        then with the most terms (``x2`` of an oscillator, ``x3`` of Bouc-Wen as in the paper's
        Figure 2e).
    data : Trajectory, optional
        Record for the phase portrait (e.g. the training data, as in the paper). Default:
        ``validation.measured``.
    window : (float, float), optional
        Time span of panel (b) in seconds. Default: see ``cycles``.
    cycles : float
        Without ``window``, panel (b) shows the last ``cycles`` periods of the forcing's
        slowest significant component (see :func:`forcing_window`).

    Returns
    -------
    matplotlib.figure.Figure
        Axes in order (a), (b), (c) and the variance axis of (c).

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify(train, library)
    >>> check = symsbl.validate_model(model, train, n_band=5)
    >>> from symsbl.plots import figure2
    >>> fig = figure2(model, check)
    >>> [ax.get_title() != "" for ax in fig.axes][:3]
    [True, True, True]
    """
    if not isinstance(validation, Validation):
        raise DataError(f"validation must be a Validation from symsbl.validate_model; received {type(validation).__name__}.")
    equation = _equation_for(model, state)
    shown = equation.lhs
    data = validation.measured if data is None else data
    if window is None:
        window = forcing_window(validation.measured, cycles)
    elif not (len(window) == 2 and window[0] < window[1]):
        raise DataError(f"window must be (t_start, t_stop) with t_start < t_stop in seconds; received {window!r}.")
    fig = _figure(figsize=(15, 4.2), layout="constrained")
    ax_a, ax_b, ax_c = fig.subplots(1, 3, width_ratios=[1, 1.5, 1.2])
    _phase_portrait(ax_a, data)
    _response(ax_b, model, validation, shown, window)
    if equation.terms:
        _coefficients(ax_c, equation)
    else:
        ax_c.set_title(f"(c) {shown}': no term kept")
        ax_c.set_axis_off()
    return fig


def coefficient_uncertainty(model: IdentifiedModel):
    """Every kept coefficient with its 3-sigma posterior interval, relative to its posterior mean.

    One panel per equation. Each term is drawn at ``coef / coef = 1`` with whiskers of
    ``3 std / |coef|``, so intervals of coefficients of very different sizes share one axis;
    the coefficient itself is written above its interval. An interval that reaches 0 (the grey
    line, shown when in range) belongs to a coefficient whose sign the data do not determine.

    Parameters
    ----------
    model : IdentifiedModel

    Returns
    -------
    matplotlib.figure.Figure
        One axes per equation, in state order.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> import os
    >>> from symsbl.plots import coefficient_uncertainty
    >>> fig = coefficient_uncertainty(symsbl.identify(train, library))
    >>> fig.savefig(os.devnull, format="png")
    """
    if not model.equations:
        raise DataError("the model has no equations to plot.")
    heights = [max(len(eq.terms), 1) for eq in model.equations]
    fig = _figure(figsize=(7, 1.0 + 0.5 * sum(heights) + 0.7 * len(heights)), layout="constrained")
    axes = fig.subplots(len(heights), 1, height_ratios=heights, squeeze=False)[:, 0]
    for ax, eq in zip(axes, model.equations):
        ax.set_title(f"{eq.lhs}'", loc="left")
        if not eq.terms:
            ax.text(0.5, 0.5, "no term kept", ha="center", va="center", transform=ax.transAxes)
            ax.set_xticks([])
            ax.set_yticks([])
            continue
        coefs, stds = eq.coefs, eq.stds
        rel = 3 * stds / np.abs(coefs)
        pos = np.arange(len(coefs))[::-1]
        ax.errorbar(np.ones_like(rel), pos, xerr=rel, fmt="o", ms=4, color=_MODEL, ecolor=_MODEL, capsize=4)
        ax.set_yticks(pos, [term_label(t.name) for t in eq.terms])
        ax.set_ylim(-0.7, len(coefs) - 0.2)
        reach = 1.6 * float(np.nanmax(rel)) if np.isfinite(np.nanmax(rel)) and np.nanmax(rel) > 0 else 0.1
        ax.set_xlim(1 - reach, 1 + reach)
        if reach >= 1:
            ax.axvline(0.0, color="0.6", lw=0.8)
        ax.axvline(1.0, color="0.85", lw=0.8, zorder=0)
        for p, c, s in zip(pos, coefs, stds):
            ax.annotate(format_uncertain(c, s), (1.0, p), xytext=(0, 5), textcoords="offset points",
                        ha="center", va="bottom", fontsize="small")
    axes[-1].set_xlabel(r"coefficient / posterior mean, with $\pm 3\sigma$ interval")
    fig.suptitle("Posterior of the kept coefficients")
    return fig


# ------------------------------------------------------------------------- discrepancy workflow
_BEFORE = "#0072b2"
_AFTER = _MODEL


def _kinematic_pair(model: IdentifiedModel) -> tuple[str | None, str]:
    """``(displacement, velocity)`` read from a base equation ``x: v`` (the last state otherwise)."""
    names = model.state_names
    for eq in model.equations:
        if len(eq.terms) == 1 and eq.terms[0].name in names and eq.terms[0].name != eq.lhs:
            return eq.lhs, eq.terms[0].name
    return None, names[-1]


def _equation_residual(model: IdentifiedModel, data: Trajectory, velocity: str) -> np.ndarray:
    """Measured ``dv/dt`` (central differences) minus the model's right-hand side for ``v``, per sample."""
    f = model.to_system().rhs_function().map(data.n_samples)
    X = np.column_stack([data.column(n) for n in model.state_names])
    U = np.column_stack([data.column(n) for n in model.input_names]) if model.input_names else np.zeros((data.n_samples, 0))
    rhs = f(X.T, U.T).full()[model.state_names.index(velocity)]
    return np.gradient(data.column(velocity), data.t) - rhs


def _before_after(ax, report, heldout: Trajectory | None, velocity: str) -> None:
    """Panel (a): the held-out record under the initial and the final model."""
    if heldout is None:
        ax.set_axis_off()
        ax.text(0.5, 0.5, "pass heldout= (the held-out Trajectory)\nto draw the response before and after",
                ha="center", va="center", transform=ax.transAxes)
        ax.set_title("(a) held-out record")
        return
    window = forcing_window(heldout, 2.0)
    keep = (heldout.t >= window[0]) & (heldout.t <= window[1])
    t = heldout.t[keep]
    if report.error_measure == "equation":
        last = report.steps[-1]
        errors = (report.steps[0].error_heldout, last.error_after if last.error_after is not None else last.error_heldout)
        reach = 0.0
        for model, err, colour, ls, label in ((report.initial, errors[0], _BEFORE, "-", "before"),
                                              (report.final, errors[1], _AFTER, "--", "after")):
            r = _equation_residual(model, heldout, velocity)[keep]
            reach = max(reach, float(np.percentile(np.abs(r), 99.5)))
            ax.plot(t, r, color=colour, lw=0.8, ls=ls, label=f"{label} (equation NRMSE {100 * err:.3g} %)")
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.set_ylim(-1.3 * reach, 1.3 * reach)  # differentiated edge samples would swamp the scale
        ax.set_ylabel(f"{velocity}' measured - model")
        ax.set_title(f"(a) held-out residual of {velocity}' (closed loop: equation error, not simulation)")
    else:
        state = velocity
        ax.plot(t, heldout.column(state)[keep], color="0.55", lw=3.0, label="measured")
        for model, colour, ls, label in ((report.initial, _BEFORE, "-", "before"), (report.final, _AFTER, "--", "after")):
            v = validate_model(model, heldout, method="rk4")
            sim = v.simulated
            inside = (sim.t >= window[0]) & (sim.t <= window[1])
            err = "diverged" if v.status != "ok" else f"NRMSE {100 * v.nrmse[state]:.3g} %"
            ax.plot(sim.t[inside], sim.column(state)[inside], color=colour, lw=1.0, ls=ls, label=f"{label} ({err})")
        ax.set_ylabel(state)
        ax.set_title(f"(a) held-out {state}: measured and re-simulated")
    ax.set_xlabel("t (s)")
    ax.set_xlim(*window)
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.3 * (high - low))  # room for the legend above the data
    ax.legend(loc="upper center", ncols=3, fontsize="small", frameon=False)


def _residual_map(fig, ax, step, displacement: str | None, velocity: str) -> None:
    """Panel (b): mean equation residual over the (displacement, velocity) plane."""
    x_edges, v_edges, grid = step.disagreement.residual_map
    reach = float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 1.0
    mesh = ax.pcolormesh(x_edges, v_edges, np.ma.masked_invalid(grid).T, cmap="RdBu_r", vmin=-reach, vmax=reach)
    colorbar = fig.colorbar(mesh, ax=ax)
    colorbar.set_label(f"mean residual of {velocity}'")
    ax.axhline(0.0, color="0.3", lw=0.6, ls=":")
    ax.ticklabel_format(style="sci", scilimits=(-2, 3))
    ax.set_xlabel(displacement or "(no displacement state)")
    ax.set_ylabel(velocity)
    ax.set_title(f"(b) where the model disagrees (iteration {step.iteration})")


def _evidence_bars(ax, step) -> None:
    """Panel (c): evidence gain of each scored candidate, the threshold, the added effect highlighted."""
    scores = [c for c in step.scores if np.isfinite(c.evidence_gain)]
    added = step.added.label if step.added is not None else None
    pos = np.arange(len(scores))[::-1]
    colours = [_AFTER if c.label == added else ("0.55" if c.admissible else "0.85") for c in scores]
    ax.barh(pos, [c.evidence_gain for c in scores], color=colours, height=0.65)
    ax.set_yticks(pos, [c.label for c in scores], fontsize="small")
    ax.axvline(step.threshold, color="k", lw=1.0, ls="--", label=f"threshold {step.threshold:.1f} nats")
    ax.axvline(0.0, color="0.6", lw=0.6)
    if scores and max(abs(c.evidence_gain) for c in scores) > 200.0:
        ax.set_xscale("symlog", linthresh=10.0)
    ax.set_xlabel("log-evidence gain (nats)")
    ax.set_title(f"(c) evidence gain per candidate ({step.decision})")
    handles, labels = ax.get_legend_handles_labels()
    if added:
        from matplotlib.patches import Patch

        handles.append(Patch(color=_AFTER))
        labels.append("added")
    if any(not c.admissible for c in scores):
        from matplotlib.patches import Patch

        handles.append(Patch(color="0.85"))
        labels.append("not admissible")
    ax.legend(handles, labels, loc="lower right", fontsize="small")


def discrepancy_figure(report, heldout: Trajectory | None = None):
    """What the discrepancy workflow found, in three panels.

    (a) The held-out record against the initial model (before) and the final model (after),
        re-simulated with :func:`symsbl.validate_model` over two periods of the forcing. For a
        report with ``error_measure == "equation"`` (closed-loop data that cannot be simulated
        open-loop, e.g. EMPS) the panel shows the velocity-equation residual instead, measured
        ``dv/dt`` (central differences) minus each model's right-hand side, and says so in its title.
    (b) The first iteration's mean equation residual over the phase plane (displacement,
        velocity), on a diverging colour scale centred at zero; empty bins are blank.
    (c) The first iteration's log-evidence gain of every scored candidate (best on top) as
        horizontal bars, the threshold it had to clear as a dashed vertical line and the added
        effect highlighted; candidates with the wrong sign are pale. With gains far above the
        threshold the axis is symmetric-logarithmic, linear within 10 nats of zero.

    Parameters
    ----------
    report : DiscrepancyReport
        From :func:`symsbl.discrepancy.discrepancy`.
    heldout : Trajectory, optional
        The held-out record the report was computed with (the report keeps the models, not the
        records). Without it panel (a) is left empty with a note.

    Returns
    -------
    matplotlib.figure.Figure
        Axes in order (a), (b), (c) and the colour bar of (b).

    Raises
    ------
    DataError
        ``report`` is not a DiscrepancyReport with at least one iteration, or ``heldout`` is not
        a Trajectory.
    """
    from .discrepancy_results import DiscrepancyReport

    if not isinstance(report, DiscrepancyReport) or not report.steps:
        got = type(report).__name__ if not isinstance(report, DiscrepancyReport) else "a report with no iteration"
        raise DataError(f"report must be a DiscrepancyReport from symsbl.discrepancy with at least one iteration; received {got}.")
    if heldout is not None and not isinstance(heldout, Trajectory):
        raise DataError(f"heldout must be a Trajectory (the held-out record); received {type(heldout).__name__}.")
    displacement, velocity = _kinematic_pair(report.initial)
    first = report.steps[0]
    fig = _figure(figsize=(17, 4.6), layout="constrained")
    ax_a, ax_b, ax_c = fig.subplots(1, 3, width_ratios=[1.5, 1.1, 1.1])
    _before_after(ax_a, report, heldout, velocity)
    _residual_map(fig, ax_b, first, displacement, velocity)
    _evidence_bars(ax_c, first)
    fig.suptitle("Discrepancy: " + report.verdict, fontsize="medium")
    return fig
