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


def as_ladder(library) -> tuple[Library, ...]:
    """``library`` as a ladder: one :class:`~symsbl.Library`, or a sequence of them each holding every term of
    the one before."""
    ladder = (library,) if isinstance(library, Library) else tuple(library) if isinstance(library, Sequence) else ()
    if not ladder or not all(isinstance(rung, Library) for rung in ladder):
        held = sorted({type(rung).__name__ for rung in ladder}) if isinstance(library, Sequence) else []
        got = (
            type(library).__name__
            if not isinstance(library, Sequence)
            else f"a {type(library).__name__} holding {', '.join(held)}"
            if held
            else f"an empty {type(library).__name__}"
        )
        raise LibraryError(
            expected(
                "library",
                "a Library, or a sequence of nested Library objects (simplest first)",
                got,
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
    """Whether an equation's fit on a richer library beats its ``current`` fit (on the library ``held``) on both
    counts, with a term ``held`` lacks (a subset of the current terms is the support search's artefact, not a
    law)."""
    return (
        len(richer.terms) < len(current.terms)
        and rule.decisive(richer.log_evidence - current.log_evidence)
        and any(t.name not in held for t in richer.terms)
    )


def climb(ladder: Sequence[Library], fit: Callable, rule: SelectionRule) -> tuple:
    """``(problem, model)`` of the ladder's climb: ``fit(library)`` gives the equation-error ``(problem,
    model)`` on one library; each equation takes its fit on each richer library in turn when it is better there by
    ``rule`` (:func:`_better`), and the returned problem is that of the richest library an equation took. A library
    the records cannot fit (fewer regression rows than candidates) ends the climb, as every richer one is larger.
    The model's ``metadata["library"]`` records each step taken: the library's size and, per equation, its terms
    before and after."""
    problem, model = fit(ladder[0])
    held = {eq.lhs: ladder[0] for eq in model.equations}
    steps = []
    for library in ladder[1:]:
        try:
            trial, richer = fit(library)
        except DataError:
            break
        fitted = {eq.lhs: eq for eq in richer.equations if not eq.fixed}
        taken = {
            eq.lhs: fitted[eq.lhs]
            for eq in model.equations
            if eq.lhs in fitted and not eq.fixed and _better(fitted[eq.lhs], eq, held[eq.lhs], rule)
        }
        if not taken:
            continue
        steps.append(
            {
                "candidates": len(library),
                "from": len(problem.library),
                "equations": {n: [len(model.equation(n).terms), len(eq.terms)] for n, eq in taken.items()},
            }
        )
        held.update(dict.fromkeys(taken, library))
        equations = tuple(taken.get(eq.lhs, eq) for eq in model.equations)
        metadata = dict(model.metadata, n_candidates=len(library))
        model = dataclasses.replace(model, equations=equations, metadata=metadata)
        problem = trial
    if steps:
        model = dataclasses.replace(model, metadata=dict(model.metadata, library=steps))
    return problem, model
