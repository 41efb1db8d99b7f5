"""The discrepancy figure: the held-out response before and after, where the model disagrees, the evidence."""

from __future__ import annotations

import numpy as np

from .._base.errors import DataError, expected
from .._data.trajectory import Trajectory
from .._figures import AFTER, BEFORE, forcing_window, new_figure
from .._model import IdentifiedModel
from .._validate.validate import validate_model
from .results import DiscrepancyReport

__all__ = ["discrepancy_figure"]


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
    U = (
        np.column_stack([data.column(n) for n in model.input_names])
        if model.input_names
        else np.zeros((data.n_samples, 0))
    )
    rhs = f(X.T, U.T).full()[model.state_names.index(velocity)]
    return np.gradient(data.column(velocity), data.t) - rhs


def _before_after(ax, report, heldout: Trajectory | None, velocity: str, displacement: str | None = None) -> None:
    """Panel (a): the held-out record under the initial and the final model (the velocity, or the displacement
    when the velocity was not measured)."""
    if heldout is None:
        ax.set_axis_off()
        ax.text(
            0.5,
            0.5,
            "pass heldout= (the held-out Trajectory)\nto draw the response before and after",
            ha="center",
            va="center",
            transform=ax.transAxes,
        )
        ax.set_title("(a) held-out record")
        return
    window = forcing_window(heldout, 2.0)
    keep = (heldout.t >= window[0]) & (heldout.t <= window[1])
    t = heldout.t[keep]
    if report.error_measure == "equation":
        last = report.steps[-1]
        errors = (
            report.steps[0].error_heldout,
            last.error_after if last.error_after is not None else last.error_heldout,
        )
        reach = 0.0
        for model, err, colour, ls, label in (
            (report.initial, errors[0], BEFORE, "-", "before"),
            (report.final, errors[1], AFTER, "--", "after"),
        ):
            r = _equation_residual(model, heldout, velocity)[keep]
            reach = max(reach, float(np.percentile(np.abs(r), 99.5)))
            ax.plot(t, r, color=colour, lw=0.8, ls=ls, label=f"{label} (equation NRMSE {100 * err:.3g} %)")
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.set_ylim(-1.3 * reach, 1.3 * reach)  # differentiated edge samples would swamp the scale
        ax.set_ylabel(f"{velocity}' measured - model")
        ax.set_title(f"(a) held-out residual of {velocity}' (closed loop: equation error, not simulation)")
    else:
        state = velocity if velocity in heldout.state_names or displacement is None else displacement
        ax.plot(t, heldout.column(state)[keep], color="0.55", lw=3.0, label="measured")
        for model, colour, ls, label in ((report.initial, BEFORE, "-", "before"), (report.final, AFTER, "--", "after")):
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
    colours = [AFTER if c.label == added else ("0.55" if c.admissible else "0.85") for c in scores]
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

        handles.append(Patch(color=AFTER))
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
        From :func:`symsbl.discrepancy`.
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
    if not isinstance(report, DiscrepancyReport) or not report.steps:
        got = type(report).__name__ if not isinstance(report, DiscrepancyReport) else "a report with no iteration"
        raise DataError(
            expected("report", "a DiscrepancyReport from symsbl.discrepancy with at least one iteration", got, raw=True)
        )
    if heldout is not None and not isinstance(heldout, Trajectory):
        raise DataError(expected("heldout", "a Trajectory (the held-out record)", type(heldout).__name__, raw=True))
    displacement, velocity = _kinematic_pair(report.initial)
    first = report.steps[0]
    fig = new_figure(figsize=(17, 4.6), layout="constrained")
    ax_a, ax_b, ax_c = fig.subplots(1, 3, width_ratios=[1.5, 1.1, 1.1])
    _before_after(ax_a, report, heldout, velocity, displacement)
    _residual_map(fig, ax_b, first, displacement, velocity)
    _evidence_bars(ax_c, first)
    fig.suptitle("Discrepancy: " + report.verdict, fontsize="medium")
    return fig
