"""Latent states: a state with its own law that no record measures (the hysteretic force of Bouc-Wen).

A state of the model that is neither a column of the data nor the velocity of a declared
position-velocity pair is latent. Its equation cannot be regressed, so :func:`identify_latent`
reconstructs it, screens its law and settles the structure by output error on what is measured:

1. :mod:`.periodic`: each record is cut into the whole periods of its input and averaged; the
   scatter of the periods gives the noise of every spectral bin (a record whose input does not
   repeat is taken whole, its ends left out of the regressions);
2. :mod:`.skeleton` (stage 1): the linear skeleton ``m y'' + c y' + k y = u`` by frequency-domain
   output error;
3. :mod:`.skeleton` and :mod:`.law` (stage 3): the split of ``(m, c, k)`` that leaves the hidden
   force ``z = u - m y'' - c y' - k y`` to a law in ``(y', z)``, and the relevance vector machine on
   the weak form of that law (a screen: full recall, low precision); in parallel, the "nothing
   hidden" alternative ``u = m y'' + c y' + k y + sum eta phi(y, y')`` (a memoryless force);
4. :func:`symsbl.refine` (stage 4): each branch (linear, memoryless, hidden) refined by output
   error on the measured position only, with term selection on the output-error evidence and the
   latent initial state as an unknown; the branch of highest Laplace evidence wins, and the hidden
   branch only by more than the per-term penalty and with a law that is not ``z' = y' g(z)`` (which
   integrates to a memoryless spring ``z = G(y)``);
5. as asked: the winner refined once more with the caller's doubts and model choice (:class:`Fitting`).

Beside states that are all measured (no structure hosts it: a level, a pressure), :mod:`.driven` screens
laws ``z' = d - a phi(z)`` simulated from a measured signal ``d`` and refines the leaders by output error
beside "nothing hidden" (``z' = 0``).

Several records are screened on the one whose position varies most and refined jointly. On a
structure of several masses (every position measured), :mod:`.hosts` finds the pair whose velocity
equation the hidden force enters and the drive of that mass by the rest of the structure; stages 1-3
run on the host with the drive as its input, and stage 4 refines every equation together.

Convention: the latent state enters the velocity equation with the coefficient ``-1/m`` of the
split, held fixed: it is a force in the units of the input (to the precision of that ``m``); on a
host the input does not act on, a force per unit mass.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings

import numpy as np

from .._base.errors import DataError, SimulationError, expected
from .._base.rule import SelectionRule
from .._model import IdentifiedModel
from .._refine import RefineOptions, refine
from .._regression.rvm import RVM
from .._symbolic.library import Library, Term
from . import driven
from .branches import Branches, Screened, margin, rivals, unused
from .hosts import drives, host_of, same_cut
from .law import WeakForm, evaluate, homogeneous_terms, screen
from .periodic import Periods, Spectra, split_periods, whole_record
from .skeleton import fit_linear, split

__all__ = ["identify_latent", "Fitting", "Periods", "Spectra", "split_periods", "whole_record"]

#: RK4 resolution of the input's fastest line, ``omega_max h``: the response is driven up to ``f_max``, which
#: the model's own modes (what ``substeps="auto"`` looks at) do not see; RK4's phase error per step is
#: ``(omega h)^5 / 120``, 4e-5 here. Measured on the benchmark (``f_max / f_s = 0.2``): 2 substeps (the
#: model's own rule) left k off by 0.14 % and the test multisine at 2.45e-7 m; 4 (this rule), 0.003 % and
#: 1.70e-7 m.
INPUT_RESOLUTION = 0.35
#: Log evidences this close are one model reached from two starts.
TIE_NATS = 1e-3


def _setting(trajectories, names, pairs, latent, library: Library) -> str:
    """The setting identified: ``"structure"``, one latent state on a structure of position-velocity pairs, every
    position measured, one input; or ``"driven"``, one latent state beside states that are all measured (a
    level of a cascade, see :mod:`.driven`)."""
    record = trajectories[0]
    members = {n for pair in pairs for n in pair}
    others = [n for n in names if n not in members and n not in latent]
    measured = all(n in record.state_names for n in names if n not in latent)
    if len(latent) != 1 or not (pairs and not others or measured):
        raise DataError(
            expected(
                "states",
                "one latent state beside measured states (e.g. --states x1,x2 with x2 a column), or on a structure "
                "of masses (--states y,v,z --kinematics y:v, or y1,v1,y2,v2,z --kinematics y1:v1,y2:v2)",
                f"states {list(names)} with kinematics {[f'{x}:{v}' for x, v in pairs]} and latent {list(latent)}",
                "a latent state is identified beside measured states, or on a structure of masses whose positions "
                "are measured",
                raw=True,
            )
        )
    missing = [n for n in (*names, *record.input_names) if n not in library.variable_names]
    if missing:
        raise DataError(
            expected(
                "library",
                f"terms of the states and inputs {[*names, *record.input_names]}",
                f"no variable {missing}",
                raw=True,
            )
        )
    if pairs and not others:
        _check_structure(record, pairs)
        return "structure"
    return "driven"


def _check_structure(record, pairs) -> None:
    """Every position of the structure measured, one input."""
    for position, _ in pairs:
        if position not in record.state_names:
            raise DataError(
                expected(
                    f"state {position!r}", "a column of the data (a measured position)", "no such column", raw=True
                )
            )
    if len(record.input_names) != 1:
        raise DataError(
            expected("inputs", "one input (the force) when a state is latent", list(record.input_names), raw=True)
        )


@dataclasses.dataclass(frozen=True)
class Fitting:
    """How ``identify`` asked for the fit: each of its options as the latent path applies it.

    Attributes
    ----------
    options : RefineOptions
        The caller's refinement options. The branches are refined with them, except that their doubts are
        reported (their evidences compare on one likelihood), ``substeps="auto"`` takes at least what the input's
        band needs (:data:`INPUT_RESOLUTION`) and more where the model's own rates ask (a stiff law: Dahl friction
        of s = 1e5 N/m and Fc = 5 N at 1 kHz took 32, where the band's 2 let the true law diverge), and the
        default ``"cubic"`` interpolation is ``"periodic"`` on a record of whole periods; the winning branch is
        then refined with them as given.
    rule : SelectionRule
        The caller's rule: its penalty settles the verdict and the screens, its model choice the winner's
        structure.
    rvm : RVM, optional
        Template of the screens' relevance vector machines.
    chunk_size, jit :
        The screens' term evaluation (:class:`~symsbl.Evaluator`).
    """

    options: RefineOptions = RefineOptions()
    rule: SelectionRule = SelectionRule()
    rvm: RVM | None = None
    chunk_size: int = 4096
    jit: object = "auto"

    @property
    def template(self) -> RVM:
        """The screens' relevance vector machine: the template's options with the rule's penalty."""
        return RVM(**dict((self.rvm or RVM()).get_params(), prune_nats=self.rule.penalty))

    def branch_options(self, periodic: bool, band_substeps: int) -> RefineOptions:
        """The options every branch is refined with; ``band_substeps``: the RK4 steps per sample the input's band
        needs, the floor of ``substeps="auto"``."""
        given = self.options
        interpolation = "periodic" if periodic and given.interpolation == "cubic" else given.interpolation
        floor = max(given.min_substeps, band_substeps) if given.substeps == "auto" else given.min_substeps
        return dataclasses.replace(given, interpolation=interpolation, min_substeps=floor, doubts="report")


def identify_latent(
    trajectories, library: Library, names, pairs, latent, fitting: Fitting = Fitting()
) -> IdentifiedModel:
    """Identify a structure of masses with one latent state from its positions alone (one mass: an oscillator).

    Parameters
    ----------
    trajectories : list of Trajectory
        Records holding the positions and the input: whole periods of a periodic input (best: the
        noise is then measured by the periods' scatter and the derivatives are exact), or transient
        records of a broadband input. The law is screened on the record whose position varies most; every
        branch is refined on all of them jointly, each from its own initial state.
    library : Library
        Candidates over the states and the input; the law of the latent state uses its homogeneous
        terms in (velocity, latent), the memoryless alternative its homogeneous terms in (position, velocity).
    names : sequence of str
        The states (positions, velocities and the latent state) in the model's order.
    pairs : sequence of (str, str)
        The position-velocity pairs, every position measured.
    latent : sequence of str
        The one latent state.
    fitting : Fitting
        The caller's options, rule and screens.

    Returns
    -------
    IdentifiedModel
        ``metadata["latent"]`` holds the verdict, each branch's log evidence and terms, the stages'
        results and times.
    """
    if _setting(trajectories, names, pairs, latent, library) == "driven":
        return _identify_driven(trajectories, library, names, pairs, latent[0], fitting)
    clock = _Clock()
    z, u = latent[0], trajectories[0].input_names[0]
    cuts, periodic, lead = _periods_of(trajectories, pairs[0][0], u)
    periods = cuts[lead]
    (y, v), stages, drive, misfit = _host(trajectories[lead], periods, periodic, library, pairs, (z, u), fitting, clock)
    symbols = {s.name(): s for s in library.variables}
    builder = Branches(tuple(symbols[n] for n in names), symbols[u], y, v, z, drive)
    starts = builder.starts(stages)
    band = max(2, math.ceil(2 * math.pi * stages.spectra.f_max / stages.spectra.fs / INPUT_RESOLUTION))
    options = fitting.branch_options(periodic, band)
    data = [r.slice(c.start) for r, c in zip(trajectories, cuts)]
    candidates = stages.candidates(library.variables)
    rule = dataclasses.replace(fitting.rule, model_choice="evidence")
    fits, caught, failed = _refine_branches(starts, dict.fromkeys(starts, data), candidates, options, rule, clock)
    verdict, best, scores = builder.verdict(fits, sum(d.n_samples for d in data), stages.n_candidates, fitting.rule)
    for w in caught[best]:  # the losing branches' warnings say only that they lose
        warnings.warn(w.message, w.category, stacklevel=3)
    chosen = _as_asked(fits[best], data, candidates.get(best), options, fitting, clock)
    final = builder.with_latent(chosen, keep=(verdict == "hidden"))
    summary = _summary(verdict, z, periods, periodic, stages, fits, scores, failed, clock)
    summary.update(records=len(data), screened_on=lead, host=y, misfit=misfit)
    summary.update(_rivals(summary, best, margin(sum(d.n_samples for d in data), stages.n_candidates, fitting.rule)))
    if drive is not None:
        summary.update(drive=drive.kind, driven=drive.driven)
    return dataclasses.replace(final, metadata=dict(final.metadata, latent=summary))


def _identify_driven(trajectories, library: Library, names, pairs, z: str, fitting: Fitting) -> IdentifiedModel:
    """One latent state beside measured states (see :mod:`.driven`): the laws screened on the longest record, the
    leaders and the "nothing hidden" model of the measured states refined on every record, the verdict by
    evidence as on a structure."""
    clock = _Clock()
    plain = Library(
        [t for t in library.terms if z not in {s.name for s in t.sympy.free_symbols}],
        [s for s in library.variables if s.name() != z],
    )
    # first: a library the measured records cannot feed fails here, by name, not as "no law"
    visible = _visible_start(trajectories, plain, [n for n in names if n != z], pairs, fitting)
    lead = int(np.argmax([r.n_samples for r in trajectories]))
    found = driven.screen(trajectories[lead], library, names, z, pairs, fitting)
    clock("law screen")
    if not found:
        raise SimulationError(
            expected(
                "data",
                f"a record on which some law {z}' = d - a phi({z}) of the library can be simulated from a measured d",
                "every candidate left its law's domain or had no equilibrium at the mean drive",
                f"add homogeneous terms of {z} alone to the library (e.g. {z}, sqrt({z}))",
                raw=True,
            )
        )
    starts, data, leaders, skipped = _driven_starts(trajectories, library, names, pairs, z, found, lead, fitting)
    starts, data = {"nothing hidden": visible, **starts}, {"nothing hidden": trajectories, **data}
    libraries = {k: library if k in leaders else plain for k in starts}
    options = dataclasses.replace(fitting.options, doubts="report")
    rule = dataclasses.replace(fitting.rule, model_choice="evidence")
    fits, caught, failed = _refine_branches(starts, data, libraries, options, rule, clock)
    scores = {k: float(f.metadata["refine"]["log_evidence"]) for k, f in fits.items()}
    structures = len({(c.drive.name, c.law.name) for c in found})  # the rates are one structure's values
    nats = margin(sum(d.n_samples for d in trajectories), structures, fitting.rule)
    best = _driven_verdict(scores, leaders, nats)
    winner = best or "nothing hidden"
    for w in caught[winner]:
        warnings.warn(w.message, w.category, stacklevel=3)
    chosen = _as_asked(fits[winner], data[winner], libraries[winner], options, fitting, clock)
    symbols = {s.name(): s for s in library.variables}
    final = chosen if best else unused(chosen, tuple(symbols[n] for n in names), z)
    summary = {
        "verdict": "hidden" if best else "nothing hidden",
        "latent": z,
        "start": "driven",
        "screened_law": (leaders[best] if best else found[0]).to_json(),
        "candidates": [c.to_json() for c in leaders.values()],
        "n_candidates": len(found),
        "branches": _branches(fits, scores),
        "failed": {**skipped, **failed},
        "records": len(trajectories),
        "screened_on": lead,
        "seconds": clock.times,
    }
    summary.update(_rivals(summary, winner, nats))
    return dataclasses.replace(final, metadata=dict(final.metadata, latent=summary))


def _branches(fits: dict, scores: dict) -> dict:
    """Each refined branch's log evidence and terms by equation, for ``metadata["latent"]["branches"]``."""
    return {
        k: {"log_evidence": scores[k], "terms": {eq.lhs: eq.names for eq in f.equations if not eq.fixed}}
        for k, f in fits.items()
    }


def _rivals(summary: dict, chosen: str, nats: float) -> dict:
    """The ``chosen`` branch, the verdict's margin ``nats`` and the branches within it (see
    :func:`.branches.rivals`)."""
    return {"chosen": chosen, "margin": nats, "rivals": rivals(summary["branches"], chosen, nats, summary["latent"])}


def _driven_starts(trajectories, library: Library, names, pairs, z: str, found, lead: int, fitting: Fitting):
    """The hidden branches of :func:`.driven.leaders`: their starts, records (with each law's latent guess) and
    screened candidates by branch name, and the leaders that could not start, with why."""
    starts, data, leaders, skipped = {}, {}, {}, {}
    for c in driven.leaders(found):
        key = f"{z}' = {c.drive.name} - a {c.law.name}"
        try:
            data[key] = driven.guesses(c, trajectories, z, names)
            starts[key] = driven.start_model(c, data[key][lead], library, names, z, pairs, fitting)
        except SimulationError as error:  # its law leaves its domain on another record
            data.pop(key, None)
            skipped[key] = str(error)
            continue
        leaders[key] = c
    return starts, data, leaders, skipped


def _driven_verdict(scores: dict, leaders: dict, penalty: float) -> str | None:
    """The hidden branch of highest log evidence when it beats "nothing hidden" by ``penalty``, else None; branches
    that converged to one model tie, and the one screened best names it."""
    top = max((scores[k] for k in leaders if k in scores), default=-math.inf)
    best = next((k for k in leaders if k in scores and scores[k] >= top - TIE_NATS), None)
    return best if best is not None and scores[best] > scores.get("nothing hidden", -math.inf) + penalty else None


def _visible_start(trajectories, library: Library, states, pairs, fitting: Fitting) -> IdentifiedModel:
    """The "nothing hidden" start: the measured states' equation-error model on a library without the latent
    state."""
    return driven.regress([r.with_states(states) for r in trajectories], library, states, pairs, fitting)


def _host(record, cut, periodic: bool, library: Library, pairs, channels, fitting: Fitting, clock):
    """The host pair of the latent state, its stages, its drive (None on one degree of freedom: the input) and
    each position's misfit: on several degrees of freedom, the pair whose linear fit leaves most beyond its
    noise, driven as the split explains best (see :mod:`.hosts`)."""
    z, u = channels
    if len(pairs) == 1:
        stages = _screen(Spectra(cut, periodic), library, (*pairs[0], z, u), fitting, clock)
        return pairs[0], stages, None, {}
    spectra = {y: Spectra(same_cut(cut, record.column(y)), periodic) for y, _ in pairs}
    inputs = {u: spectra[pairs[0][0]].u}
    values = {n: x for y, v in pairs for n, x in ((y, spectra[y].y), (v, spectra[y].v))} | inputs
    (y, v), misfit = host_of(spectra, pairs, inputs)
    screened = [
        (_screen(spectra[y].driven_by(d.u), library, (y, v, z, u), fitting, clock, values), d)
        for d in drives(spectra, pairs, inputs, (y, v))
    ]
    stages, drive = min(screened, key=lambda s: s[0].skeleton.criterion)
    return (y, v), stages, drive, misfit


def _periods_of(trajectories, y: str, u: str):
    """Each record's whole periods (or the record whole), whether every record is periodic, and the record the
    law is screened on: the one whose position varies most (where a nonlinear law shows most)."""
    splits = [split_periods(r.t, r.column(u), r.column(y)) for r in trajectories]
    periodic = all(c is not None for c in splits)
    cuts = [
        c if periodic and c is not None else whole_record(r.t, r.column(u), r.column(y))
        for r, c in zip(trajectories, splits)
    ]
    lead = int(np.argmax([np.std(r.column(y)) for r in trajectories]))
    return cuts, periodic, lead


def _as_asked(fit: IdentifiedModel, data, library, options: RefineOptions, fitting: Fitting, clock) -> IdentifiedModel:
    """The winning branch refined once more with the caller's doubts and model choice, where they differ from the
    branches' (which report their doubts and choose by evidence)."""
    doubted = bool(fit.metadata["refine"].get("doubts")) and fitting.options.doubts != "report"
    chooses = options.select and fitting.rule.model_choice != "evidence"  # a structure the rule still chooses
    if not (doubted or chooses):
        return fit
    asked = dataclasses.replace(options, doubts=fitting.options.doubts)
    try:
        again = refine(fit, data, library=library, options=asked, selection=fitting.rule)
    except (SimulationError, np.linalg.LinAlgError) as error:  # the branch's own fit stands, and says why
        meta = dict(fit.metadata["refine"], as_asked=f"failed: {error}")
        return dataclasses.replace(fit, metadata=dict(fit.metadata, refine=meta))
    finally:
        clock("as asked")
    return again


def _refine_branches(starts, data: dict, candidates, options: RefineOptions, rule: SelectionRule, clock):
    """Each branch refined from its start on its records ``data[branch]``: the fits, the warnings of each, the
    branches that failed."""
    fits, caught = {}, {}
    failed = {}
    for name, start in starts.items():
        with warnings.catch_warnings(record=True) as caught[name]:
            warnings.simplefilter("always")
            try:
                fits[name] = refine(start, data[name], library=candidates.get(name), options=options, selection=rule)
            except (SimulationError, np.linalg.LinAlgError) as error:  # this branch's start runs away
                failed[name] = str(error)
        clock(f"{name} branch")
    if not fits:
        raise SimulationError(
            expected(
                "data",
                "a record some branch (linear, memoryless, hidden) can simulate",
                f"every refinement diverged: {next(iter(failed.values()))}",
                raw=True,
            )
        )
    return fits, caught, failed


def _summary(verdict, z, periods, periodic, stages, fits, scores, failed, clock) -> dict:
    """The ``metadata["latent"]`` record: the verdict, the stages' results, each branch's evidence and times."""
    return {
        "verdict": verdict,
        "latent": z,
        "periodic": periodic,
        "period_samples": periods.length if periodic else None,
        "periods": periods.n_periods if periodic else 0,
        "dropped_periods": periods.dropped,
        "f_max": stages.spectra.f_max,
        "noise_std_of_average": math.sqrt(stages.spectra.noise_var),
        "linear_skeleton": stages.linear.to_json(),
        "split_skeleton": stages.skeleton.to_json(),
        "screened_law": [stages.law_terms[i].name for i in stages.law.active_],
        "screened_force": [stages.force_terms[i - 3].name for i in stages.memory.active_ if i >= 3],
        "branches": _branches(fits, scores),
        "failed": failed,
        "seconds": clock.times,
    }


def _screen(spectra: Spectra, library: Library, channels, fitting: Fitting, clock, values=None) -> Screened:
    """Stages 1-3: the linear skeleton, its split from the hidden force, and the screens of the hidden law and of
    the memoryless alternative; ``channels`` names the position, velocity, latent state and input, ``values`` the
    samples of the structure's other variables."""
    y, v, z, u = channels
    linear = fit_linear(spectra)
    clock("linear skeleton")
    symbols = {s.name(): s for s in library.variables}
    law_terms = homogeneous_terms(library.terms, {v, z})
    if v not in [t.name for t in law_terms]:
        law_terms = [Term(symbols[v]), *law_terms]
    force_terms = homogeneous_terms(library.terms, {y, v}, exclude={y, v, "1"})
    weak = WeakForm(spectra)
    samples = {y: spectra.y, v: spectra.v, u: spectra.u} | (values or {})
    law_columns = evaluate(law_terms, library.variables, fitting.chunk_size, fitting.jit)

    def columns_of(zvalues):
        return law_columns({**samples, z: zvalues})

    linear_column = [t.name for t in law_terms].index(v)
    skeleton = split(lambda m, c, k: weak.unexplained(columns_of, m, c, k, linear_column), linear)
    zhat = spectra.force(skeleton.m, skeleton.c, skeleton.k)
    law = screen(weak.stats(weak.filter(columns_of(zhat)), weak.derivative(zhat)), template=fitting.template)
    forces = (
        evaluate(force_terms, library.variables, fitting.chunk_size, fitting.jit)({**samples, z: zhat})
        if force_terms
        else np.zeros((spectra.N, 0))
    )
    memory = screen(
        weak.stats(weak.filter(np.column_stack([spectra.a, spectra.v, spectra.y, forces])), weak.filter(spectra.u)),
        free=(0, 1, 2),
        template=fitting.template,
    )
    clock("split and screen")
    return Screened(spectra, linear, skeleton, law_terms, law, force_terms, memory)


class _Clock:
    def __init__(self):
        self.start = time.perf_counter()
        self.times = {}

    def __call__(self, stage: str):
        now = time.perf_counter()
        self.times[stage] = round(self.times.get(stage, 0.0) + now - self.start, 2)  # a stage run again adds up
        self.start = now
