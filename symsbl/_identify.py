"""Identification: trajectories x library -> :class:`~symsbl._model.IdentifiedModel`.

1. :func:`~symsbl._regression.rows.regression_stats` reduces the records to the sufficient statistics of
   the regression of the state derivatives on the library (one Gram shared by every equation);
2. one :class:`~symsbl._regression.rvm.RVM` per state equation is fitted from the shared statistics;
3. an evidence-guided search improves each support and near-equivalent candidates are resolved
   by parsimony (:mod:`symsbl._regression.support`): the equation-error model;
4. by default the output-error refinement (:func:`symsbl.refine`) re-estimates every coefficient
   from the simulation error of the measured states and selects terms on its evidence.

The model is expressed in the data's physical units: a term ``sin(x1)`` is the sine of the
measured ``x1``. Columns are normalised only inside the RVM.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import numpy as np

from ._base.errors import DataError, ParameterError, RefineWarning, SimulationError, expected
from ._base.rule import SelectionRule
from ._data.trajectory import Trajectory, noise_levels
from ._derivatives.kinematics import complete_states, kinematic_triples, latent_states, velocity_noise
from ._latent import Fitting, identify_latent
from ._model import FitMethod, IdentifiedModel
from ._model.outputs import AccelerationOutput, AlgebraicOutput, state_outputs
from ._refine import refine, refine_or_keep
from ._refine.diagnostics import noisy_input_names
from ._refine.inputnoise import AGREEMENT, DRAWS, disagreement, input_noise_covariance, widened
from ._refine.options import RefineOptions, as_options, requested
from ._regression.band import lower_edge
from ._regression.fit import fit_stats, selection_rule
from ._regression.ladder import as_ladder, climb
from ._regression.path import validated_equations
from ._regression.rows import as_trajectories, regression_stats
from ._regression.rvm import RVM
from ._symbolic.library import Library

__all__ = ["identify"]


def identify(
    data,
    library: Library | Sequence[Library],
    *,
    derivative="weak",
    rvm: RVM | None = None,
    chunk_size: int = 4096,
    jit="auto",
    equivalence_nats: float | None = None,
    states=None,
    kinematics=None,
    refine: bool | RefineOptions = True,
    refine_options: RefineOptions | dict | None = None,
    selection: SelectionRule | None = None,
    outputs=(),
) -> IdentifiedModel:
    """Identify one sparse ODE per state from sampled trajectories.

    Parameters
    ----------
    data : Trajectory or list of Trajectory
        Measured or simulated channels and inputs; several records (a test campaign at several levels, say)
        are fitted jointly, each with its own initial state and noise level. Every state gets an equation;
        kinematic ones (``x1' = x2``) are found, not assumed, unless declared in ``kinematics``.
    library : Library or sequence of Library
        Candidate terms, e.g. :func:`symsbl.paper`; or a ladder of nested libraries, simplest first (the
        command line's default: the ``paper`` library of degree 3, then 4): each equation takes its
        equation-error fit on the next library when that holds fewer terms at a higher evidence by the
        selection rule's ``margin_nats`` (the law needs a term only the richer library has);
        ``metadata["library"]`` records the steps taken, and the refinement draws on the richest library
        taken. A latent state is identified on the first.
    derivative : str or derivative strategy
        How the targets are built: ``"weak"`` (default; integral form on non-overlapping
        windows), ``"central"``, ``"point"`` (the paper's), ``"savgol"``.
    rvm : RVM, optional
        Template estimator (options are copied; it is not modified). Default ``RVM()``.
    chunk_size : int
        Rows per chunk in the dictionary evaluation.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.
    equivalence_nats : float, optional
        Near-equivalent candidates (default: the selection rule's, 2 nats): a kept term is swapped for a
        simpler candidate (see :func:`complexity`) when the swap costs less than this many nats of log evidence, and
        every candidate within this margin is reported as indistinguishable. At 16 mm of
        displacement ``x1``, ``sin(x1)`` and ``tan(x1)`` differ by parts in 10^4 and the
        evidence cannot separate them; parsimony then keeps ``x1``.
    states : sequence of str, optional
        The model's states, in order (default: the data's). A state absent from the data is
        unmeasured: the velocity of a pair in ``kinematics``, or else *latent*, a state with its own
        law that no record holds (the hysteretic force of a Bouc-Wen oscillator). One latent state is
        identified on a structure of position-velocity pairs (every position measured; on several, the
        hidden force's host is found) and one input, from one record or several jointly, best of
        whole periods of a periodic input; or beside states that are all measured, with a law
        ``z' = d - a phi(z) + ...`` driven by one measured signal (the upper level of two tanks in cascade)
        (see *Latent states* in the documentation): ``metadata["latent"]`` then
        gives the verdict
        ("hidden" or "nothing hidden"), and the model is always refined by output error: ``refine=False`` and a
        ``derivative`` other than ``"weak"`` are refused there, and every other option acts (the refinement's
        options on every branch, the selection rule on the verdict, the screens and the winner's structure).
    kinematics : mapping or str, optional
        Position-velocity pairs, ``{"x1": "x2"}`` or ``"x1:x2,x3:x4"``: ``x1' = x2`` holds exactly,
        the equation is fixed and either member may be unmeasured. A third name, ``"x1:x2:a1"`` (or
        ``{"x1": ("x2", "a1")}``), is the column of an accelerometer that measures ``x2'``: it is the velocity
        equation's target in the equation error and an output of the model (:class:`~symsbl.AccelerationOutput`)
        in the output error. Members that are not measured are reconstructed for the equation error (a
        velocity by a smoothing derivative of its position, a position or velocity by integrating a measured
        velocity or acceleration, its drift filtered out) and are initial-state unknowns of the output error.
    refine : bool or RefineOptions
        Re-estimate every coefficient by output error (:func:`symsbl.refine`) after the
        equation-error fit, and select terms on the output-error evidence (default; a
        :class:`~symsbl.RefineOptions` says how). ``False`` returns the equation-error model.
    refine_options : RefineOptions or dict, optional
        The refinement's options (a dict of :class:`~symsbl.RefineOptions` fields is accepted too);
        give them here or as ``refine``, not both.
    selection : SelectionRule, optional
        The rule terms are kept by, in the equation error and in the refinement (default
        :class:`symsbl.SelectionRule`: the extended BIC's penalty per term, parsimony within 2 nats).
        ``equivalence_nats`` and the template ``rvm``'s ``prune_nats`` are parts of it that may be
        given on their own.
    outputs : sequence of str
        Columns with an equation of their own, ``y = sum_j c_j phi_j(x, u)`` over the library (a force cell,
        :class:`~symsbl.AlgebraicOutput`): identified like a state equation, and fitted with them by output
        error.

    Returns
    -------
    IdentifiedModel

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> print(symsbl.identify(train, library, refine=False))   # equation error only
    x1' = 1.0002(5e-4) x2
    x2' = -9990(23) x1 - 20.07(0.06) x2 - 9.999e8(8e5) x1^3 + 0.9992(7e-4) F
    >>> model = symsbl.identify(train, library)                 # refined by output error
    >>> print(model)
    x1' = 0.99997(6e-5) x2
    x2' = -1.0004e4(3) x1 - 19.999(0.002) x2 - 1.000e9(2e5) x1^3 + 1.00002(7e-5) F
    >>> model.equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    trajectories = as_trajectories(data)
    ladder = as_ladder(library)
    rule = selection_rule(selection, rvm, equivalence_nats)
    options = requested(refine, refine_options)
    algebraic = _algebraic(outputs)
    columns = trajectories[0].state_names
    extra = set(algebraic)
    names = tuple(n for n in columns if n not in extra) if states is None else tuple(states)
    triples = kinematic_triples(kinematics, names)
    pairs = tuple((x, v) for x, v, _ in triples)
    accelerations = {v: a for _, v, a in triples if a is not None}
    if states is None:
        names = tuple(n for n in names if n not in set(accelerations.values()))
        triples = kinematic_triples(kinematics, names)
    _check_columns(columns, names, accelerations, algebraic)
    latent = latent_states(names, columns, pairs, accelerations)
    if latent:
        asked = _check_latent(latent, accelerations, algebraic, derivative, options)
        fitting = Fitting(options=asked, rule=rule, rvm=rvm, chunk_size=chunk_size, jit=jit)
        return identify_latent(trajectories, ladder[0], names, pairs, latent, fitting)
    present = {v: a for v, a in accelerations.items() if a in columns}
    completed, unmeasured = complete_states(
        trajectories, names, pairs, present, keep=tuple(present.values()) + algebraic
    )
    band = _integrated_band(trajectories, pairs, present, unmeasured)

    def fit(rung: Library, like=None):
        problem = regression_stats(
            completed,
            rung,
            derivative=derivative if like is None else like.derivative,
            chunk_size=chunk_size,
            jit=jit,
            states=names,
            derivatives=present,
            outputs=algebraic,
            band=band,
        )
        return problem, fit_stats(problem, rvm=rvm, kinematics=pairs, selection=rule)

    problem, model = climb(ladder, fit, rule)
    measured = tuple(n for n in names if n in columns)
    observed = (
        state_outputs(measured)
        + tuple(AccelerationOutput(a, v) for v, a in present.items())
        + tuple(AlgebraicOutput(n) for n in algebraic)
    )
    if unmeasured or present or algebraic:
        how = ", ".join(f"{n} by {_how(n, pairs, present, columns)}" for n in unmeasured)
        model = dataclasses.replace(
            model,
            measured=measured,
            outputs=observed if present or algebraic else (),
            metadata=dict(model.metadata, **({"unmeasured_estimate": how} if how else {})),
        )
    if options is None:
        return model
    refined = refine_or_keep(model, trajectories, library=problem.library, options=options, selection=rule)
    estimated = _estimated(trajectories, completed, unmeasured, pairs, columns, present)
    return _reported(model, refined, completed, problem, rvm, rule, estimated=estimated, fitted=(trajectories, options))


def _integrated_band(trajectories, pairs, present: dict, unmeasured) -> float:
    """The lower band edge (Hz) of the accelerations a position or velocity was integrated from, on the longest
    record: the equation error's rows are fitted above it, where the integrals hold; 0.0 when none was."""
    longest = max(trajectories, key=lambda r: r.n_samples)
    integrated = [present[v] for x, v in pairs if v in present and {x, v} & set(unmeasured)]
    return lower_edge(longest.t, [longest.column(a) for a in integrated])


#: The largest relative noise of a velocity estimated from its position for the equation error on it to be
#: reported: its errors in variables then bias a linear term by about its square (1e-6), and a sign(v) flips on
#: about that share of the samples (1e-3 at most). An encoder's quantisation (EMPS): 5e-6; 1 % noise on a
#: position: 0.006.
ESTIMATE_NOISE = 1e-3


def _estimated(trajectories, completed, unmeasured, pairs, columns, accelerations) -> bool:
    """Whether a state the records lack was reconstructed too roughly for the equation error on it to be reported:
    by integration (its drift removed, not known; a velocity with a measured acceleration in ``accelerations`` is
    integrated from it), or by a smoothing derivative noisier than :data:`ESTIMATE_NOISE` (:func:`velocity_noise`)."""
    derived = {v: x for x, v in pairs if v in unmeasured and x in columns and v not in accelerations}
    if any(n not in derived for n in unmeasured):
        return True
    return any(
        velocity_noise(c.t, r.column(x), c.column(v)) > ESTIMATE_NOISE
        for r, c in zip(trajectories, completed)
        for v, x in derived.items()
    )


def _check_latent(latent, accelerations: dict, algebraic: tuple, derivative, options) -> RefineOptions:
    """The refinement's options of the latent path, once what it cannot honour is refused (every other option acts
    on it: see :class:`symsbl._latent.Fitting`): latent states are identified from position records only, by
    output error, their law screened on the weak form of the record."""
    if options is None:
        raise ParameterError(
            expected(
                "refine",
                "True or a RefineOptions when a state is latent (its law is chosen by output error on what is "
                "measured: there is no equation-error model to return)",
                False,
                "drop refine=False (--no-refine)",
            )
        )
    if not (isinstance(derivative, str) and derivative == "weak"):
        raise ParameterError(
            expected(
                "derivative",
                "'weak' when a state is latent (its law is screened on the weak form of the record's periods)",
                derivative,
                "drop derivative (--derivative, --overlap)",
            )
        )
    if accelerations or algebraic:
        given = list(accelerations.values()) + list(algebraic)
        raise ParameterError(
            expected(
                "states",
                "latent states with position records only (accelerations and "
                "algebraic outputs with latent states are not identified yet)",
                f"latent {list(latent)} with outputs {given}",
                raw=True,
            )
        )
    return options


def _reported(
    start: IdentifiedModel,
    refined: IdentifiedModel,
    records,
    problem,
    rvm,
    rule: SelectionRule,
    estimated: bool,
    fitted: tuple = ((), None),
) -> IdentifiedModel:
    """The output error's model, or, where its likelihood does not hold (:func:`symsbl._refine.diagnostics.doubts`:
    process or input noise, a closed loop), the equation error's with each equation's structure validated by
    cross-validation (:mod:`symsbl._regression.path`); where a measured input is noisy and the loop open, the
    output error's fit of that structure with its covariance widened by refits (:mod:`symsbl._refine.inputnoise`).
    ``fitted``: the records and options the refinement had. ``metadata["estimator"]`` says which and why."""
    info = refined.metadata.get("refine", {}) if refined.fit is FitMethod.OUTPUT_ERROR else {}
    doubts = info.get("doubts", [])
    used = {"used": refined.fit.value, "doubts": doubts}
    doubted = bool(doubts) and info.get("adapted", True)
    noisy = bool(info.get("input_noise")) and not info.get("closed_loop")
    if not doubted or estimated:  # a rough reconstruction would bias the equation error
        out = _widened(refined, refined, fitted, used) if noisy and doubted else None
        return out or dataclasses.replace(refined, metadata=dict(refined.metadata, estimator=used))
    template = RVM(**dict((rvm or RVM()).get_params(), prune_nats=rule.penalty))
    used = dict(used, used="equation-error", output_error=_coefficients(refined))
    try:
        folds = [
            regression_stats(piece, problem.library, derivative=problem.derivative, **problem.targets).stats
            for piece in _folds(records)
        ]
    except DataError as error:  # folds too short for the library: the equation error's own selection stands
        meta = dict(
            start.metadata, refine=refined.metadata.get("refine", {}), estimator=dict(used, validated=f"no: {error}")
        )
        return dataclasses.replace(start, metadata=meta)
    again = regression_stats(
        [_noisier(r) for r in records], problem.library, derivative=problem.derivative, **problem.targets
    )
    model, path = validated_equations(start, problem, folds, template, rule, again.stats)
    meta = dict(start.metadata, refine=refined.metadata.get("refine", {}), estimator=dict(used, validated="yes"))
    model = dataclasses.replace(model, metadata=meta, path=path)
    if noisy:  # output error is precise here, and the refits make its posterior honest
        out = _widened(model, refined, fitted, used)
        if out is None:  # the output error's fit of the structure ran away: the equation error's model stands
            return model
        stat, level = disagreement(model, out)
        if stat <= level:
            return dataclasses.replace(out, path=path)
        line = (
            f"the equation error's and output error's coefficients disagree beyond their errors (chi-square "
            f"{stat:.3g} against {level:.3g} at {100 * AGREEMENT:g} %): the structure lacks a term the record hides "
            "from output error, so the equation error's model is reported"
        )
        warnings.warn(RefineWarning(line), stacklevel=3)
        estimator = dict(meta["estimator"], doubts=list(doubts) + [line], disagreement=[stat, level])
        return dataclasses.replace(model, metadata=dict(meta, estimator=estimator))
    return model


def _widened(structure: IdentifiedModel, refined: IdentifiedModel, fitted: tuple, used: dict):
    """The output error's fit of ``structure`` (``refined`` where that is its structure) on ``fitted`` (the
    records and options of the refinement), its covariance widened by refits with each noisy input's noise
    drawn again; the equation error's coefficients, where ``structure`` is its model, kept in
    ``metadata["estimator"]["equation_error"]``. None where the fit or too many refits run away."""
    records, options = fitted
    once = dataclasses.replace(as_options(options), select=False, doubts="report")

    def refit(recs, model):
        with warnings.catch_warnings():  # the doubts are the first fit's, reported once
            warnings.simplefilter("ignore", RefineWarning)
            return refine(model, recs, options=once)

    same = structure.fit is FitMethod.OUTPUT_ERROR or _names(structure) == _names(refined)
    try:
        fit = refined if same else refit(records, structure)
    except (SimulationError, np.linalg.LinAlgError):
        return None
    noisy = noisy_input_names(records, refined.measured_names, refined.input_names)
    levels = [{n: lv[n] for n in noisy} for r in records for lv in [noise_levels(r)]]
    extra = input_noise_covariance(fit, records, levels, lambda recs: refit(recs, fit))
    if extra is None:
        return None
    estimator = dict(used, used="output-error", input_noise={"draws": DRAWS, "levels": levels})
    if structure.fit is not FitMethod.OUTPUT_ERROR:
        estimator = dict(estimator, structure="equation-error, validated", equation_error=_coefficients(structure))
        estimator.pop("output_error", None)
    model = widened(fit, extra)
    first = refined.metadata.get("refine", {})  # the doubts and their adaptation are the first fit's
    kept = {k: first[k] for k in ("doubts", "closed_loop", "input_noise", "biased", "adapted") if k in first}
    refine_meta = dict(model.metadata.get("refine", {}), **kept)
    return dataclasses.replace(model, metadata=dict(model.metadata, refine=refine_meta, estimator=estimator))


def _coefficients(model: IdentifiedModel) -> dict:
    """``{lhs: {term: [coef, std]}}`` of the fitted equations, as ``metadata["estimator"]`` records another fit."""
    return {eq.lhs: {t.name: [t.coef, t.std] for t in eq.terms} for eq in model.equations if not eq.fixed}


def _names(model: IdentifiedModel) -> tuple:
    return tuple(tuple(sorted(eq.names)) for eq in model.equations)


def _algebraic(outputs) -> tuple[str, ...]:
    """The names of the algebraic outputs (a sequence of column names, or comma-separated text)."""
    if isinstance(outputs, str):
        outputs = [n.strip() for n in outputs.split(",") if n.strip()]
    if not isinstance(outputs, (list, tuple)) or not all(isinstance(n, str) and n for n in outputs):
        raise ParameterError(
            expected("outputs", "names of columns with an equation of their own (a force cell)", outputs)
        )
    return tuple(outputs)


def _check_columns(columns, names, accelerations: dict, algebraic) -> None:
    """Every algebraic output is a column; outputs are named unlike the states; a pair's acceleration, when its
    column is absent, is not needed."""
    clash = sorted(set(algebraic) & (set(names) | set(accelerations.values())))
    if clash:
        raise ParameterError(
            expected("outputs", "columns named unlike the states and the accelerations", clash, raw=True)
        )
    absent = [n for n in algebraic if n not in columns]
    if absent:
        raise DataError(expected(f"outputs {','.join(absent)}", "columns of the data", "no such column", raw=True))


def _how(name: str, pairs, accelerations: dict, columns) -> str:
    """How the equation error reconstructed a state the records lack."""
    for x, v in pairs:
        if name == v and x in columns and v not in accelerations:  # with its acceleration, integrated from it
            return "smoothing derivative"
        if name in (x, v):
            return "integration"
    return "integration"


def _noisier(record: Trajectory) -> Trajectory:
    """``record`` with its own noise added again (each column's white-noise level, :func:`noise_levels`):
    what this adds to an equation's residual is what the noise puts there, the floor of its error."""
    levels = noise_levels(record)
    rng = np.random.default_rng(0)

    def noisy(values, names):
        return values + np.array([levels[n] for n in names]) * rng.standard_normal(values.shape)

    return Trajectory(
        record.t,
        noisy(record.states, record.state_names),
        noisy(record.inputs, record.input_names),
        record.state_names,
        record.input_names,
    )


#: Contiguous folds of each record for the equation error's cross-validation.
FOLDS = 5


def _folds(records) -> list:
    """The records cut into :data:`FOLDS` contiguous stretches each (a record of fewer than 5 folds of 64 samples
    stays whole)."""
    out = []
    for r in records:
        k = FOLDS if r.n_samples >= FOLDS * 64 else 1
        cuts = (np.arange(k + 1) * r.n_samples) // k
        out += [r.slice(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:])]
    return out
