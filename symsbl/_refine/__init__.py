"""Output-error refinement: fit the trajectories, not only the derivatives.

:func:`refine` re-estimates every coefficient of an identified model by minimising the simulation
error of the *measured* states, each weighted by its own noise level, on one or several records
(each with its own unknown initial state), and returns the Laplace posterior and evidence:

- :mod:`.problem`: what is estimated (the free coefficients) and the records' layout;
- :mod:`.sensitivity`: one compiled pass for the simulation, its sensitivities and the
  Gauss-Newton blocks of every segment;
- :mod:`.solver`: Levenberg-Marquardt with the segments' initial states eliminated, continuation in
  the segment length (multiple shooting without continuity constraints, merged until one segment
  spans each record);
- :mod:`.laplace`: posterior, evidence, prior precisions, Bayesian model reduction;
- :mod:`.candidates`: what the selection tries (the equation-error runners-up, look-alikes and terms of one
  variable) and the prior of each;
- :mod:`.screen`: library terms scored by the output error when a state is not measured;
- :mod:`.selection`: term selection on the output-error evidence;
- :mod:`.engine`: one fit of one structure, and the refined model;
- :mod:`.initial`: initial states for validation.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from .._base.blas import one_blas_thread
from .._base.errors import ParameterError, RefineWarning, SimulationError, expected
from .._base.progress import Progress, stopwatch
from .._base.rule import DEFAULT as DEFAULT_RULE
from .._base.rule import SelectionRule
from .._data.residuals import LEVEL as RESIDUAL_LEVEL
from .._data.trajectory import Trajectory
from .._model import IdentifiedModel
from .._symbolic.library import Library
from .candidates import Rebased, extend, prior
from .candidates import candidates as propose
from .diagnostics import as_record, doubts, loop_possible, noisy_inputs, residual_tests
from .engine import Engine, Settings, record_horizon, residual_fraction
from .options import MAX_SAMPLES, RefineOptions, as_options
from .path import choose_structure
from .problem import check_records, window_plan
from .result import to_model
from .reuse import shared_passes
from .rows import design_rows, state_guess
from .screen import screen_terms
from .selection import _every_term_clears
from .selection import select as select_terms
from .solver import PHI_STOP, Solution
from .swap import swap_terms

__all__ = ["refine", "refine_or_keep", "MAX_SAMPLES", "RefineOptions"]


def _windows(records: list[Trajectory], max_samples: int) -> tuple[list[Trajectory], str]:
    """The records, or evenly spaced windows of them totalling about ``max_samples`` samples."""
    plan, note = window_plan([r.n_samples for r in records], max_samples)
    return [records[k] if (a, b) == (0, records[k].n_samples) else records[k].slice(a, b) for k, a, b in plan], note


@one_blas_thread()  # many small products and least squares: on busy cores, threads cost more than they bring
@shared_passes()  # the structures fitted in one refinement share compiled passes
def refine(
    model: IdentifiedModel,
    data,
    *,
    measured=None,
    library: Library | None = None,
    select: bool = True,
    interpolation: str = "cubic",
    substeps="auto",
    smooth: bool = True,
    max_samples: int = MAX_SAMPLES,
    jit="auto",
    options: RefineOptions | None = None,
    selection: SelectionRule | None = None,
) -> IdentifiedModel:
    """Re-estimate a model's coefficients by output error, with the Laplace posterior and evidence.

    Every coefficient of the equations that are not fixed (kinematic equations ``x' = v`` are exact)
    is re-estimated by minimising the simulation error of the measured states, each weighted by its
    own noise precision (re-estimated from the residuals), with the model's prior precisions
    (re-estimated by MacKay's rule) as the Gaussian prior of the coefficients. Each record keeps its
    own unknown initial state (unmeasured components included), integrated out of the posterior.

    Parameters
    ----------
    model : IdentifiedModel
        The starting point and structure, typically from :func:`symsbl.identify` (equation error).
    data : Trajectory or list of Trajectory
        Records with the measured states and the model's inputs (several records are fitted jointly).
    measured : sequence of str, optional
        The states to fit (default: the model's states present in the data). A column of a state that
        is not measured (a reconstruction of a latent state) is used only as the starting guess of its
        trajectory (without one, zeros; the RK4 steps are chosen on the state as the starting model
        simulates it).
    library : Library, optional
        The candidate library of the equation-error fit: with it, the equation-error runners-up and
        indistinguishable terms are tried too.
    select : bool
        Select terms on the output-error evidence (remove terms whose removal raises the evidence by
        more than ``1/2 log N + log M`` nats; add runners-up that raise it). When a state is not
        measured, library terms are also screened by their output-error score (see *Displacement only* in
        the output-error explanation) and the best are tried; ``metadata["refine"]["screened"]`` lists
        them. Then, there or when the first fit's residual is coloured, each selected term (or pair) is
        offered in exchange for a library term the equation's terms nearly span, and an exchange a refit
        confirms is kept (see *Swaps* there).
    interpolation : {"cubic", "linear", "periodic"}
        How the measured input runs between samples: a cubic spline (default; a linear hold biases
        stiff, hardening systems by up to two posterior standard deviations at 16 kHz), a linear
        hold, or band-limited periodic interpolation for records of whole periods.
    substeps : int or "auto"
        RK4 steps per sample; "auto" takes enough that ``h |lambda|max <= 0.25``.
    smooth : bool
        Fit ``sign(a)`` as ``tanh(a / eps)`` with ``eps = 3e-4 std(a)``: fixed-step RK4 of a sign is
        discontinuous in the coefficients and its Gauss-Newton curvature twice too large; the model
        returned keeps ``sign``.
    max_samples : int
        Samples refined on at most; longer data contribute evenly spaced windows (the posterior then
        reflects those samples only, a conservative width).
    jit : {"auto", True, False}
        Compile the passes with a C compiler when available.
    options : RefineOptions, optional
        All of the above in one object (then leave those keywords at their defaults).
    selection : SelectionRule, optional
        The rule terms are kept by (default :class:`symsbl.SelectionRule`: the extended BIC's penalty per term,
        the simpler of near-equivalent structures).

    Returns
    -------
    IdentifiedModel
        ``fit`` is ``FitMethod.OUTPUT_ERROR``; coefficients, standard deviations, prior precisions,
        the joint covariance, per-equation noise of the measured states and the log evidence come
        from the output-error posterior; ``metadata["refine"]`` says what was fitted and how.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192),
    ...                         inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1))
    >>> train = train.with_noise(0.01, seed=0)
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.refine(symsbl.identify(train, library), train, library=library)
    >>> model.fit.value, model.equation("x2").names
    ('output-error', ['x1', 'x2', 'x1**3', 'F'])
    >>> round(model.equation("x2").coef("x1**3") / -1e9, 3)
    1.0
    """
    if not isinstance(model, IdentifiedModel):
        raise ParameterError(expected("model", "an IdentifiedModel", type(model).__name__, raw=True))
    records, measured = check_records(model, data, measured)
    given = RefineOptions(
        select=select, interpolation=interpolation, substeps=substeps, smooth=smooth, max_samples=max_samples, jit=jit
    )
    opts = _options(given, options)
    rule = _rule(selection)
    if not any(not eq.fixed and eq.terms for eq in model.equations):
        raise ParameterError(expected("model", "at least one equation with terms to fit", "none", raw=True))
    clock = stopwatch()
    used, note = _windows(records, opts.max_samples)
    settings = Settings(
        interpolation=opts.interpolation,
        substeps=opts.substeps,
        smooth=opts.smooth,
        jit=opts.jit,
        noise=opts.noise,
        doubts=opts.doubts,
        min_substeps=opts.min_substeps,
    )
    select = opts.select
    rebased = None
    if library is not None:
        if not isinstance(library, Library):
            raise ParameterError(expected("library", "a symsbl Library (or None)", type(library).__name__, raw=True))
        rebased = Rebased(library, model, _ranges(model, used, measured))
    refined, rounds, proposed, last = _rounds(model, used, measured, settings, select, rebased, rule)
    info = refined.metadata["refine"]
    stuck = info["biased"] and info["adapted"]  # output error biased: the structure it was given stays
    if not stuck and select and rule.model_choice != "evidence":  # the structure that validates
        n_candidates = len(library) if library is not None else max(sum(len(eq.terms) for eq in refined.equations), 2)
        refined = choose_structure(
            model, refined, used, measured, settings, rule, n_candidates, info["short_segments"], seed=last
        )
    meta = refined.metadata["refine"]
    if len(used) != len(records):  # windows of the records were fitted: their noise levels are not the records'
        for channel in meta.get("noise", {}).values():
            channel.pop("innovation_std_by_record", None)
    meta.update(
        samples=note,
        smoothed_sign=opts.smooth,
        rounds=rounds,
        screened={
            lhs: list(dict.fromkeys(n for p in proposed for n in p.get(lhs, ())))
            for lhs in dict.fromkeys(k for p in proposed for k in p)
        },
        with_poles=list(rebased.with_poles) if rebased is not None else [],
        seconds=round(clock(), 3),
    )
    if meta["hypersensitive"]:
        _warn_hypersensitive(meta, float(np.mean([r.dt for r in used])))
    if meta["doubts"] or not meta["hypersensitive"]:  # a hypersensitive record's residual follows its input anyway
        _warn(meta)
    return refined


def _ranges(model: IdentifiedModel, records, measured) -> dict:
    """``{variable: (low, high)}`` of every state and input over ``records`` (a state not measured: its guess, a
    velocity from its position)."""
    guess = state_guess(model, records, measured)
    out = {n: (float(np.min(guess[:, k])), float(np.max(guess[:, k]))) for k, n in enumerate(model.state_names)}
    for name in model.input_names:
        u = np.concatenate([r.column(name) for r in records])
        out[name] = (float(np.min(u)), float(np.max(u)))
    return out


def _options(given: RefineOptions, options) -> RefineOptions:
    """The refinement's options: the keywords ``given`` or ``options``, not both."""
    if options is not None and given != RefineOptions():
        raise ParameterError(
            expected(
                "options",
                "the refinement's options given once: as keywords or as a RefineOptions",
                "both",
                "pass only options=RefineOptions(...)",
                raw=True,
            )
        )
    return as_options(given if options is None else options, "options")


def _rounds(model, used, measured, settings, select, rebased, rule) -> tuple[IdentifiedModel, int, list, Solution]:
    """The rounds of screening and selection until the structure repeats: the model (its metadata's ``swaps``
    those of every round), the number of rounds, the terms each round's screen proposed and the last fit."""
    offered = select and rebased is not None
    hidden = offered and bool(set(model.state_names) - set(measured))
    # with a state not measured, the screen and the selection first work on short segments, where a term missing
    # from the start cannot yet make the simulation run off the record; the structure found is then fitted whole
    refined, screened, last = _refine_once(
        model, used, measured, settings, select, rebased, offered, rule, short=hidden
    )
    rounds, seen, proposed = 1, {_structure(model)}, [screened]
    swaps = list(refined.metadata["refine"]["swaps"])
    while screened and rounds < MAX_ROUNDS and _structure(refined) not in seen:
        # the screen scored its candidates at the equation-error structure; from the new one it may see others
        seen.add(_structure(refined))
        refined, screened, last = _refine_once(
            refined, used, measured, settings, select, rebased, offered, rule, short=hidden
        )
        proposed.append(screened)
        swaps += refined.metadata["refine"]["swaps"]
        rounds += 1
    if hidden:
        refined, _, last = _refine_once(refined, used, measured, settings, select, rebased, False, rule)
        rounds += 1
    refined.metadata["refine"]["swaps"] = swaps
    return refined, rounds, proposed, last


def _warn_hypersensitive(meta: dict, dt: float) -> None:
    """One RefineWarning: the model amplifies a state error beyond :data:`PHI_STOP` within the record."""
    warnings.warn(
        RefineWarning(
            f"output-error refinement: the record is hypersensitive (chaotic-like): the model amplifies a state "
            f"error {PHI_STOP:g}-fold within {meta['horizon']} samples ({meta['horizon'] * dt:.3g} s), so it was "
            f"fitted on segments of {meta['segment_length']} samples and its response over the whole record hangs on "
            "rounding-level changes of its coefficients and initial state; judge it over short horizons (validate "
            "does)"
        ),
        stacklevel=3,
    )


def _warn(meta: dict) -> None:
    """One RefineWarning: the likelihood does not hold (in a closed loop no term was selected; else the fit was held
    to short segments), or the residual depends on an input (model error: the structure is not validated)."""
    if meta["doubts"] and not meta["adapted"]:
        if meta["biased"]:  # non-white innovations alone are recorded: the fit is the usual one
            warnings.warn(
                RefineWarning(
                    "output-error refinement: its likelihood is doubtful here ("
                    + "; ".join(meta["doubts"])
                    + "); the fit and its evidence are reported as they are (doubts='report')"
                ),
                stacklevel=3,
            )
        return
    if meta["biased"]:
        warnings.warn(RefineWarning(_biased(meta)), stacklevel=3)
        return
    if meta["doubts"]:
        warnings.warn(
            RefineWarning(
                "output-error refinement: the residual is not measurement noise the noise model describes ("
                + "; ".join(meta["doubts"])
                + f"), so it was fitted on segments of at most {meta['short_segments']} "
                "samples, each from its own initial state, where no disturbance accumulates (identify reports the "
                "equation error's model where every state is measured or finely estimated)"
            ),
            stacklevel=3,
        )
        return
    worse = [
        f"{t['channel']} on {k} ({r:.2g} x the threshold)"
        for t in meta["residual"]
        for k, r in t["input_ratio"].items()
        if r > 1
    ]
    if worse:
        warnings.warn(
            RefineWarning(
                "output-error refinement: the residual depends on the input: " + ", ".join(worse) + f" (the "
                f"{100 * (1 - RESIDUAL_LEVEL):g} % cross-correlation test): the model misrepresents how the input "
                "acts (a missing or wrong term, the input's interpolation, a delay), and its structure is not "
                "validated by this record"
            ),
            stacklevel=3,
        )


def _biased(meta: dict) -> str:
    """The warning of a fit whose output error is biased (a closed loop, a noisy input): what identify reports."""
    what = " and ".join(
        w
        for w, on in (
            ("the record looks closed-loop", meta["closed_loop"]),
            ("the measured input is noisy", meta["input_noise"]),
        )
        if on
    )
    reported = (
        "the equation error's model"
        if meta["closed_loop"]
        else "the equation error's structure (elsewhere the one fitted) with output error's coefficients, their "
        "covariance widened by refits with the input's noise drawn again"
    )
    return (
        f"output-error refinement: {what}, where output error is biased, so no term was selected on its evidence "
        f"(where every state is measured or finely estimated, identify reports {reported}): "
        + "; ".join(meta["doubts"])
    )


#: A white-noise fit's residual is coloured below this effective fraction of its samples (white noise of a few
#: hundred samples reads below 1 by chance).
COLOURED = 0.9

#: Rounds of screening and selection at most.
MAX_ROUNDS = 3


def _structure(model: IdentifiedModel) -> tuple:
    return tuple(tuple(sorted(eq.names)) for eq in model.equations)


def _rule(selection) -> SelectionRule:
    if selection is None:
        return DEFAULT_RULE
    if not isinstance(selection, SelectionRule):
        raise ParameterError(expected("selection", "a SelectionRule (or None)", type(selection).__name__, raw=True))
    return selection.check()


def _refine_once(
    model: IdentifiedModel,
    used,
    measured,
    settings: Settings,
    select: bool,
    library: Rebased | None,
    offered: bool,
    rule: SelectionRule,
    short: bool = False,
):
    """One fit of ``model``'s structure, then (``select``) the selection; the refined model, the terms the
    screen proposed and the fit it reports. ``short``: every fit on segments of the first length of the
    continuation."""
    guess = state_guess(model, used, measured)
    candidates, twins = {}, {}
    if select and library is not None:
        candidates, twins = propose(model, library, design_rows(model, used, guess))
    engine = Engine(model, used, measured, settings, candidates, guess=guess)
    if short:
        engine.longest = engine.length0
    alpha = prior(engine)
    theta0 = np.zeros(len(engine.positions))
    theta0[engine.base] = engine.param.theta0[engine.base]
    screened: dict = {}
    swaps: list = []
    with Progress("output-error refinement", total=2 if select else 1, unit="fits") as bar:
        sol = engine.fit(engine.base, theta0, alpha)
        bar.update()
        held = settings.interpolation == "hold"  # a digital controller's held output is known exactly
        noisy = () if held else noisy_inputs(used, measured, model.input_names)
        adapt = settings.doubts == "adapt"
        n_obs = int(sum(r.n_samples for r in used)) * len(measured)
        n_candidates = library.offered if library is not None else max(engine.base.size, 2)
        selected = select and not (adapt and noisy)  # a selection would absorb the input noise's bias
        tests = residual_tests(engine, sol) if selected and adapt and loop_possible(engine) else None
        if tests is not None and doubts(tests).closed_loop:  # and a loop's, which the start already shows
            selected = False  # (EMPS from its encoder: 16 min of CPU selecting on a biased evidence)
        nats = rule.nats_per_term(n_obs, n_candidates)

        def per_term(wide):  # a residual correlated with every candidate counts fewer independent samples
            return nats / residual_fraction(engine, wide)

        if selected:
            engine, sol, alpha, screened, swaps = _selection(
                engine, sol, alpha, (candidates, twins), measured, library if offered else None, rule, nats
            )
            bar.update()
        if selected or tests is None:  # the loop and the innovations' whiteness: on the structure selected
            tests = residual_tests(engine, sol)
        doubted = doubts(tests, noisy)
        if adapt and doubted and not doubted.biased and sol.length > engine.length0:
            # process noise: segments short enough that no disturbance accumulates in them
            engine.longest = engine.length0
            sol = engine.fit(sol.active, sol.theta, sol.alpha)
            if selected:  # every kept term clears the penalty on the fit reported
                sol = select_terms(engine, sol, alpha, per_term, twins, rule)
            tests = residual_tests(engine, sol)
        fraction = residual_fraction(engine, sol)
    info = _info(engine, sol, (screened, swaps), fraction, tests, doubted, adapt)
    return to_model(engine, sol, info), screened, sol


def _selection(engine: Engine, sol, alpha, proposed: tuple, measured, library: Rebased | None, rule, nats: float):
    """The term selection from the first fit ``sol`` of ``engine`` at ``nats`` per term (``proposed``: the
    candidates and look-alike pairs of :func:`~symsbl._refine.candidates.candidates`); with ``library``, the
    output-error screen before it when a state is not measured, and the swaps after it then or when the first
    fit's residual is coloured. The engine, fit and prior precisions it ends with, the terms the screen
    proposed and the swaps made."""
    candidates, twins = proposed
    first, first_sol = engine, sol
    # a state estimated, not measured, may have hidden a term from the equation error; a coloured residual of
    # the equation error's structure, that one of its terms stands in for others
    hidden = library is not None and bool(set(engine.model.state_names) - set(measured))
    swapping = library if hidden or (library is not None and _coloured(engine, sol)) else None
    screened: dict = {}
    if hidden and library is not None:
        once = dataclasses.replace(engine.settings, jit=False)  # a few passes: compiling would cost more
        model, n_candidates = engine.model, library.offered
        screened = screen_terms(
            lambda recs, cands: Engine(model, recs, measured, once, cands),
            model,
            engine.records,
            sol,
            engine,
            library,
            lambda n: rule.nats_per_term(n, n_candidates),
        )
        engine, sol, alpha = extend(engine, sol, alpha, candidates, screened, library)
    wide = engine
    sol = select_terms(engine, sol, alpha, lambda fit: nats / residual_fraction(wide, fit), twins, rule)
    swaps: list = []
    if swapping is not None:
        engine, sol, alpha, swaps = swap_terms(engine, sol, alpha, swapping, rule)
        if first.settings.noise == "auto" and sol.noise.order and _names(engine, sol) != _names(first, first_sol):
            sol = _noise_again(engine, sol)
    return engine, sol, alpha, screened, swaps


def _noise_again(engine: Engine, sol):
    """``sol`` refitted with its noise model's order chosen again on its own residual (``sol`` if the refit
    fails): the order was chosen on the first fit's, coloured by a structure the selection replaced."""
    penalty = float(sol.penalty) if sol.penalty is not None else 0.0
    order = engine.noise
    engine.noise = "auto"
    try:
        return _every_term_clears(engine, engine.fit(sol.active, sol.theta, sol.alpha, warm=sol), penalty)
    except (SimulationError, np.linalg.LinAlgError):
        engine.noise = order
        return sol


def _names(engine: Engine, sol) -> set:
    """The (state, term) names of the coefficients ``sol`` holds."""
    return {engine.names[int(k)] for k in sol.active}


def _coloured(engine: Engine, sol) -> bool:
    """The residual of the fit ``sol`` is not white: its noise model is coloured, or (white noise assumed) its
    autocorrelation lowers the effective samples."""
    return bool(sol.noise.order) or residual_fraction(engine, sol) < COLOURED


def _info(engine: Engine, sol, found: tuple, fraction: float, tests, doubted, adapt: bool) -> dict:
    """What the model file records of one refinement: its segments, evidence, the terms its screen proposed and
    the swaps it made (``found``), residual tests and doubts."""
    screened, swaps = found
    reach = record_horizon(engine, sol)
    return {
        "refine": {  # to_model adds the substeps, the interpolation and the noise model
            "segment_length": int(sol.length),
            "stages": sol.stages,
            "horizon": reach,
            "hypersensitive": reach is not None,
            "penalty": sol.penalty,
            "passes": int(sol.n_pass),
            "log_evidence": float(sol.posterior.log_evidence),
            "screened": screened,
            "swaps": swaps,
            "effective_fraction": round(fraction, 4),
            "residual": [as_record(t) for t in tests],
            "doubts": list(doubted.reasons),
            "closed_loop": doubted.closed_loop,
            "input_noise": doubted.input_noise,
            "biased": doubted.biased,
            "short_segments": engine.longest,
            "adapted": adapt,
        }
    }


def refine_or_keep(
    model: IdentifiedModel,
    records,
    *,
    library: Library | None,
    options: RefineOptions | dict | None = None,
    note: str | None = None,
    selection: SelectionRule | None = None,
) -> IdentifiedModel:
    """The refinement :func:`symsbl.identify` runs by default: :func:`refine` with ``options``; when the
    simulation diverges on the records (a model the data cannot integrate), a
    :class:`~symsbl.RefineWarning` and the equation-error model, with ``metadata["refine"]["failed"]``
    saying why. ``note`` replaces the record of which samples were used (windows read by a caller).
    """
    options = as_options(options)
    try:
        refined = refine(model, records, library=library, options=options, selection=selection)
    except (SimulationError, np.linalg.LinAlgError) as error:  # numerical failure: the equation error stands
        warnings.warn(str(error), RefineWarning, stacklevel=3)
        return dataclasses.replace(model, metadata=dict(model.metadata, refine={"failed": str(error)}))
    if note is None:
        return refined
    return dataclasses.replace(
        refined, metadata=dict(refined.metadata, refine=dict(refined.metadata["refine"], samples=note))
    )
