"""A ladder of libraries: each equation from the simplest library that holds its law.

A library of one polynomial degree may lack the law: a Bouc-Wen hysteresis of exponent 3 needs ``|v| z^3`` and
``v |z|^3``, terms of degree 4, and a degree-3 library spreads it over many small terms (17 where the law has 3).
A ladder is a sequence of nested libraries, simplest first, each tried in turn. Each equation's equation-error fit
on a richer library replaces its current fit when it is better on both counts, fewer terms and a decisively higher
evidence (by the selection rule's margin, as a named winner must beat its runner-up), with a term the current
library lacks. Where neither library holds the law the two fits are rival approximations: a saturating stiffness's
equation error on an estimated velocity, 8 terms at degree 3 and 7 at degree 4, differs by 0.1 nats (the
hysteresis above: 547), and stays on the simpler library. An equation whose law the simpler library holds keeps its
equation-error fit there (a richer library only adds terms to it); the refinement then draws on the richest library
taken, for every equation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

from .._base.errors import DataError, LibraryError, expected
from .._base.rule import SelectionRule
from .._symbolic.library import Library

__all__ = ["as_ladder", "climb"]


def _received(library) -> str:
    """What ``identify`` received in place of a ladder, for its error."""
    if isinstance(library, (str, bytes)) or not isinstance(library, Sequence):
        return f"{type(library).__name__} {library!r}" if isinstance(library, (str, bytes)) else type(library).__name__
    if not library:
        return f"an empty {type(library).__name__}"
    wrong = {k: type(rung).__name__ for k, rung in enumerate(library) if not isinstance(rung, Library)}
    return f"a {type(library).__name__} holding " + ", ".join(f"{name} at [{k}]" for k, name in wrong.items())


def as_ladder(library) -> tuple[Library, ...]:
    """``library`` as a ladder: one :class:`~symsbl.Library`, or a sequence of them each holding every term of
    the one before."""
    many = isinstance(library, Sequence) and not isinstance(library, (str, bytes))
    ladder = (library,) if isinstance(library, Library) else tuple(library) if many else ()
    if not ladder or not all(isinstance(rung, Library) for rung in ladder):
        raise LibraryError(
            expected(
                "library",
                "a Library, or a sequence of nested Library objects (simplest first)",
                _received(library),
                "build each with symsbl.paper, symsbl.polynomial or symsbl.custom",
                raw=True,
            )
        )
    for k, (simpler, richer) in enumerate(zip(ladder, ladder[1:])):
        missing = [n for n in simpler.names if n not in richer]
        if missing or simpler.variable_names != richer.variable_names:
            got = f"terms {missing[:3]} missing" if missing else f"variables {richer.variable_names}"
            raise LibraryError(
                expected(
                    f"library[{k + 1}]",
                    f"every term and the variables {simpler.variable_names} of library[{k}]",
                    got,
                    "order the libraries simplest first, each built on the same variables",
                    raw=True,
                )
            )
    return ladder


def _better(richer, current, held: Library, rule: SelectionRule) -> bool:
    """Whether an equation's fit on a richer library beats its ``current`` fit (on the library ``held``, both on
    the same regression rows) on both counts, with a term ``held`` lacks (a subset of the current terms is the
    support search's artefact, not a law)."""
    return (
        len(richer.terms) < len(current.terms)
        and rule.decisive(richer.log_evidence - current.log_evidence)
        and any(t.name not in held for t in richer.terms)
    )


class _Current:
    """Each equation's current fit, the library it came from and the regression rows it was fitted on (the
    resolved derivative), with fits of those libraries on another library's rows made once each."""

    def __init__(self, ladder, problem, model):
        self.model = model
        self.held = {eq.lhs: ladder[0] for eq in model.equations}
        self.rows = {eq.lhs: problem.derivative for eq in model.equations}
        self.cache: dict = {}

    def on_rows_of(self, trial, fit: Callable, lhs: str):
        """The current fit of ``lhs``, refitted on the rows of the problem ``trial`` when its own differ."""
        if self.rows[lhs] == trial.derivative:
            return self.model.equation(lhs)
        key = (id(self.held[lhs]), id(trial))
        if key not in self.cache:
            self.cache[key] = {eq.lhs: eq for eq in fit(self.held[lhs], like=trial)[1].equations}
        return self.cache[key][lhs]

    def take(self, taken: dict, library: Library, trial) -> None:
        self.held.update(dict.fromkeys(taken, library))
        self.rows.update(dict.fromkeys(taken, trial.derivative))
        equations = tuple(taken.get(eq.lhs, eq) for eq in self.model.equations)
        metadata = dict(self.model.metadata, n_candidates=len(library))
        self.model = dataclasses.replace(self.model, equations=equations, metadata=metadata)


def climb(ladder: Sequence[Library], fit: Callable, rule: SelectionRule) -> tuple:
    """``(problem, model)`` of the ladder's climb: ``fit(library, like=None)`` gives the equation-error ``(problem,
    model)`` on one library (on the regression rows of the problem ``like`` when given: a richer library may
    resolve a shorter weak-form window, and evidences compare on the same rows only); each equation takes its fit
    on each richer library in turn when it is better there by ``rule`` (:func:`_better`), and the returned problem
    is that of the richest library an equation took. A library the records cannot fit (fewer regression rows than
    candidates, values past a double's range) ends the climb, as every richer one holds it. The model's
    ``metadata["library"]`` records each step taken (the library's size and, per equation, its terms before and
    after and the size of the library it came from), ``metadata["library_refused"]`` the library that ended
    the climb and why."""
    problem, model = fit(ladder[0])
    current = _Current(ladder, problem, model)
    steps: list[dict] = []
    refused = None
    for library in ladder[1:]:
        try:
            trial, richer = fit(library)
        except DataError as error:
            refused = {"candidates": len(library), "why": str(error)}
            break
        fitted = {eq.lhs: eq for eq in richer.equations if not eq.fixed}
        taken = {
            eq.lhs: fitted[eq.lhs]
            for eq in current.model.equations
            if eq.lhs in fitted
            and not eq.fixed
            and len(fitted[eq.lhs].terms) < len(eq.terms)  # before any refit on the richer library's rows
            and _better(fitted[eq.lhs], current.on_rows_of(trial, fit, eq.lhs), current.held[eq.lhs], rule)
        }
        if not taken:
            continue
        before = {
            n: [len(current.model.equation(n).terms), len(eq.terms), len(current.held[n])] for n, eq in taken.items()
        }
        steps.append({"candidates": len(library), "from": len(problem.library), "equations": before})
        current.take(taken, library, trial)
        problem = trial
    extra: dict = {"library": steps} if steps else {}
    if refused is not None:
        extra["library_refused"] = refused
    model = current.model
    return problem, dataclasses.replace(model, metadata=dict(model.metadata, **extra)) if extra else model
