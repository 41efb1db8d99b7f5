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

from ._base.errors import DataError, ParameterError, expected
from ._base.format import format_uncertain
from ._data.trajectory import Trajectory
from ._discrepancy.figures import discrepancy_figure
from ._figures import BAND, MEASURED, MODEL, POSTERIOR, PRIOR, forcing_window, new_figure, term_label
from ._model import Equation, IdentifiedModel
from ._validate.validate import Validation

__all__ = [
    "figure2",
    "coefficient_uncertainty",
    "discrepancy_figure",
    "model_path_figure",
    "term_label",
    "forcing_window",
]


def _equation_for(model: IdentifiedModel, state: str | None) -> Equation:
    if not model.equations:
        raise DataError(expected("model", "a model with at least one equation to plot", "none", raw=True))
    if state is None:
        # The equation that carries the nonlinearity: most nonlinear terms (x3' of Bouc-Wen, as
        # in the paper's Figure 2e), then most terms; ties go to the later state (x2' rather
        # than the kinematic x1' = x2).
        def weight(eq):
            return sum(not (t.sympy.is_Symbol or t.sympy.is_Number) for t in eq.terms), len(eq.terms)

        return max(reversed(model.equations), key=weight)
    try:
        return model.equation(state)
    except ParameterError:
        raise DataError(expected("state", f"one of the model's states {list(model.state_names)}", state)) from None


def _phase_portrait(ax, data: Trajectory) -> None:
    x = data.states[:, 0]
    if data.states.shape[1] >= 2:
        y, ylabel = data.states[:, 1], data.state_names[1]
    else:
        y, ylabel = np.gradient(x, data.dt), f"d{data.state_names[0]}/dt (finite difference)"
    ax.plot(x, y, color=MEASURED, lw=0.6)
    ax.ticklabel_format(style="sci", scilimits=(-2, 3))
    ax.set_xlabel(data.state_names[0])
    ax.set_ylabel(ylabel)
    ax.set_title("(a) measured phase portrait")


def _response(ax, model: IdentifiedModel, validation: Validation, state: str, window) -> None:
    measured, simulated = validation.measured, validation.simulated
    t0, t1 = window
    keep = (measured.t >= t0) & (measured.t <= t1)
    ax.plot(measured.t[keep], measured.column(state)[keep], color=MEASURED, lw=1.0, label="measured")
    sim_keep = (simulated.t >= t0) & (simulated.t <= t1)
    if sim_keep.any():
        ax.plot(
            simulated.t[sim_keep],
            simulated.column(state)[sim_keep],
            color=MODEL,
            lw=1.0,
            ls="--",
            label="identified model",
        )
    band, label = validation.predictive_band, r"3$\sigma$ predictive band"
    if band is None:
        band, label = validation.band, r"3$\sigma$ band (coefficients)"
    if band is not None:
        k = model.state_names.index(state)
        lower, upper = band[0][:, k], band[1][:, k]
        ax.fill_between(measured.t[keep], lower[keep], upper[keep], color=BAND, alpha=0.35, lw=0, label=label)
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
    right.plot(pos, prior, "o", color=PRIOR, label=r"prior variance $1/\alpha$")
    right.plot(pos, posterior, "s", mfc="none", color=POSTERIOR, label=r"posterior variance $\sigma^2$")
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
        :attr:`~symsbl.Validation.predictive_band`, where new measurements should fall;
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
        raise DataError(
            expected("validation", "a Validation from symsbl.validate_model", type(validation).__name__, raw=True)
        )
    equation = _equation_for(model, state)
    shown = equation.lhs
    data = validation.measured if data is None else data
    if window is None:
        window = forcing_window(validation.measured, cycles)
    elif not (len(window) == 2 and window[0] < window[1]):
        raise DataError(expected("window", "(t_start, t_stop) with t_start < t_stop in seconds", window))
    fig = new_figure(figsize=(15, 4.2), layout="constrained")
    ax_a, ax_b, ax_c = fig.subplots(1, 3, width_ratios=[1, 1.5, 1.2])
    _phase_portrait(ax_a, data)
    # a latent state has no measured response: panel (b) then shows the first measured state
    measured = validation.measured.state_names
    response = shown if shown in measured else next(n for n in model.state_names if n in measured)
    _response(ax_b, model, validation, response, window)
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
        raise DataError(expected("model", "a model with at least one equation to plot", "none", raw=True))
    heights = [max(len(eq.terms), 1) for eq in model.equations]
    fig = new_figure(figsize=(7, 1.0 + 0.5 * sum(heights) + 0.7 * len(heights)), layout="constrained")
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
        ax.errorbar(np.ones_like(rel), pos, xerr=rel, fmt="o", ms=4, color=MODEL, ecolor=MODEL, capsize=4)
        ax.set_yticks(pos, [term_label(t.name) for t in eq.terms])
        ax.set_ylim(-0.7, len(coefs) - 0.2)
        reach = 1.6 * float(np.nanmax(rel)) if np.isfinite(np.nanmax(rel)) and np.nanmax(rel) > 0 else 0.1
        ax.set_xlim(1 - reach, 1 + reach)
        if reach >= 1:
            ax.axvline(0.0, color="0.6", lw=0.8)
        ax.axvline(1.0, color="0.85", lw=0.8, zorder=0)
        for p, c, s in zip(pos, coefs, stds):
            ax.annotate(
                format_uncertain(c, s),
                (1.0, p),
                xytext=(0, 5),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize="small",
            )
    axes[-1].set_xlabel(r"coefficient / posterior mean, with $\pm 3\sigma$ interval")
    fig.suptitle("Posterior of the kept coefficients")
    return fig


def model_path_figure(model: IdentifiedModel):
    """The model path of an identification: cross-validated free-run error and penalised evidence against the
    number of terms (the Pareto front of error against size), the chosen structure marked, one row of panels per
    path (per equation where each has its own); and the residual
    tests of the reported model (Ljung-Box p-value of each channel's innovations, and the largest
    cross-correlation with each input against its threshold).

    Parameters
    ----------
    model : IdentifiedModel
        From :func:`symsbl.identify` with output-error refinement (``model.path`` not empty).

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> import symsbl, symsbl.plots
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> train = symsbl.simulate(symsbl.systems.duffing(), symsbl.time_grid(1.0, 4096),
    ...                         inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)
    ...                         ).with_noise(0.01, seed=0)
    >>> model = symsbl.identify(train, symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F]))
    >>> fig = symsbl.plots.model_path_figure(model)
    >>> len(fig.axes)
    3
    """
    if not isinstance(model, IdentifiedModel) or not len(model.path):
        raise DataError(
            expected(
                "model",
                "an identified model with a model path (identify with output-error refinement)",
                "none" if isinstance(model, IdentifiedModel) else type(model).__name__,
                raw=True,
            )
        )
    groups: dict = {}  # one path per set of equations fitted together: a path per equation gets its own panels
    for e in model.path:
        groups.setdefault(tuple(lhs for lhs, _ in e.terms), []).append(e)
    fig = new_figure(figsize=(11.0, 3.8 * len(groups)), layout="constrained")
    grid = fig.add_gridspec(len(groups), 3)
    for row, (lhs, entries) in enumerate(groups.items()):
        ax_cv, ax_ev = fig.add_subplot(grid[row, 0]), fig.add_subplot(grid[row, 1])
        which = " of " + ", ".join(f"{name}'" for name in lhs) if len(groups) > 1 else ""
        _path_panels(ax_cv, ax_ev, entries, which, legend=row == 0)
    ax_res = fig.add_subplot(grid[:, 2])
    tests = model.metadata.get("refine", {}).get("residual", [])
    labels, values = [], []
    for t in tests:
        labels.append(f"{t['channel']}: whiteness")
        values.append(min(1.0 / max(t["whiteness_p"], 1e-300) * 0.01, 1e3))  # 1 at p = 0.01
        for name, r in t["input_ratio"].items():
            labels.append(f"{t['channel']} vs {name}")
            values.append(r)
        for name, r in t["feedback_ratio"].items():
            labels.append(f"{name}<-{t['channel']} (feedback)")
            values.append(r)
    if values:
        y = np.arange(len(values))
        ax_res.barh(y, values, color=[MODEL if v > 1 else POSTERIOR for v in values])
        ax_res.axvline(1.0, color=MEASURED, lw=1, ls="--")
        ax_res.set_yticks(y, labels, fontsize=7)
        ax_res.set_xscale("log")
        ax_res.set_xlabel("statistic / its 99 % threshold")
    ax_res.set_title("residual tests")
    return fig


def _path_panels(ax_cv, ax_ev, entries: list, which: str, legend: bool) -> None:
    """One model path: cross-validated error and penalised evidence against the number of terms, the chosen
    structure ringed once."""
    from matplotlib.ticker import MaxNLocator  # matplotlib is there: new_figure checked it

    for ax in (ax_cv, ax_ev):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    sizes = np.array([e.n_terms for e in entries])
    cv = np.array([100 * e.cv_error for e in entries])
    se = np.array([100 * e.cv_se if np.isfinite(e.cv_se) else 0.0 for e in entries])
    finite = np.isfinite(cv)
    ax_cv.errorbar(sizes[finite], cv[finite], yerr=se[finite], fmt="o", color=MEASURED, ms=4, capsize=2)
    chosen = [k for k, e in enumerate(entries) if e.chosen][:1]
    for k in chosen:
        if finite[k]:
            ax_cv.plot(sizes[k], cv[k], "o", ms=10, mfc="none", mec=MODEL, mew=2, label="chosen")
    ax_cv.set_yscale("log")
    ax_cv.set_xlabel("free terms")
    ax_cv.set_ylabel("cross-validated free-run error (%)")
    ax_cv.set_title(f"model path{which}")
    if chosen and legend:
        ax_cv.legend(frameon=False, fontsize=8, loc="upper center")
    objective = np.array([e.objective for e in entries])
    ax_ev.plot(sizes, objective - np.max(objective), "s", color=PRIOR, ms=4)
    for k in chosen:
        ax_ev.plot(sizes[k], objective[k] - np.max(objective), "s", ms=10, mfc="none", mec=MODEL, mew=2)
    ax_ev.set_xlabel("free terms")
    ax_ev.set_ylabel("penalised log evidence - best (nats)")
    ax_ev.set_yscale("symlog")
    ax_ev.set_title(f"evidence{which}")
