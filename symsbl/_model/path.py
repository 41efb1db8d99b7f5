"""The model path of an identification: candidate structures from the simplest to the richest, each with its
evidence and its cross-validated free-run error, and the one chosen."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["PathEntry", "ModelPath", "PATH_SOURCES"]

#: Where a structure of a model path comes from.
PATH_SOURCES = ("evidence", "equation error", "path")


@dataclass(frozen=True)
class PathEntry:
    """One candidate structure of a model path.

    Attributes
    ----------
    terms : tuple of (str, tuple of str)
        Per fitted equation, its left-hand side and its terms' names.
    n_terms : int
        Free terms.
    log_evidence : float
        Laplace log evidence of the output-error fit (nats), under the fit's noise model; the path's fits stop
        within a nat of their optimum (they rank structures), the chosen structure's fit is carried on.
    objective : float
        The log evidence minus the selection rule's penalty per term.
    cv_error : float
        Cross-validated free-run error: each fold simulated by the fit without it, RMS error relative to
        each channel's spread, mean over the folds and channels (``inf``: a fold's simulation diverged).
    cv_se : float
        Standard error of the fold-by-fold difference from the best cross-validated structure (0 for it).
    source : str
        Where the structure comes from: ``"evidence"`` (the term selection's), ``"equation error"``, or
        ``"path"`` (a backward elimination step).
    chosen : bool
    screened : bool
        A backward step whose refit was stopped after a few passes, its error already far above the best's:
        its error and evidence are where the refit stood then, not at its optimum (printed as source
        ``path, screened``; written to a model file only when true).

    Examples
    --------
    >>> from symsbl import PathEntry
    >>> entry = PathEntry((("v", ("x", "F")),), 2, -120.5, -130.2, 0.031, 0.002, "path")
    >>> entry.names("v"), PathEntry.from_json(entry.to_json()) == entry
    (['x', 'F'], True)
    """

    terms: tuple
    n_terms: int
    log_evidence: float
    objective: float
    cv_error: float
    cv_se: float
    source: str
    chosen: bool = False
    screened: bool = False

    def names(self, lhs: str) -> list[str]:
        """The terms of the equation of ``lhs``."""
        return list(dict(self.terms).get(lhs, ()))

    def to_json(self) -> dict:
        finite = lambda v: float(v) if math.isfinite(v) else None  # noqa: E731 - JSON has no inf
        return {
            "terms": {lhs: list(names) for lhs, names in self.terms},
            "n_terms": self.n_terms,
            "log_evidence": finite(self.log_evidence),
            "objective": finite(self.objective),
            "cv_error": finite(self.cv_error),
            "cv_se": finite(self.cv_se),
            "source": self.source,
            "chosen": self.chosen,
        } | ({"screened": True} if self.screened else {})

    @classmethod
    def from_json(cls, doc: dict) -> PathEntry:
        def num(v):
            return math.inf if v is None else float(v)

        return cls(
            tuple((lhs, tuple(names)) for lhs, names in doc["terms"].items()),
            int(doc["n_terms"]),
            num(doc["log_evidence"]),
            num(doc["objective"]),
            num(doc["cv_error"]),
            num(doc["cv_se"]),
            str(doc["source"]),
            bool(doc["chosen"]),
            bool(doc.get("screened", False)),
        )


@dataclass(frozen=True)
class ModelPath:
    """The candidate structures of an identification, simplest first, with the chosen one marked.

    Prints as a table: terms, evidence, cross-validated error and its standard error against the best.

    Examples
    --------
    >>> from symsbl import ModelPath, PathEntry
    >>> path = ModelPath((PathEntry((("v", ("x",)),), 1, -200.0, -205.0, 0.2, 0.05, "path"),
    ...                   PathEntry((("v", ("x", "F")),), 2, -120.0, -130.0, 0.03, 0.0, "evidence", chosen=True)))
    >>> len(path), path.chosen.names("v")
    (2, ['x', 'F'])
    """

    entries: tuple[PathEntry, ...] = ()
    rule: str = ""

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self):
        return iter(self.entries)

    def __getitem__(self, k: int) -> PathEntry:
        return self.entries[k]

    @property
    def chosen(self) -> PathEntry | None:
        return next((e for e in self.entries if e.chosen), None)

    def __str__(self) -> str:
        if not self.entries:
            return "(no model path)"
        rows = ["  terms  log evidence   penalised   CV error (%)   +- SE   source          structure"]
        for e in self.entries:
            structure = "; ".join(f"{lhs}: {', '.join(names) or '0'}" for lhs, names in e.terms)
            cv = f"{100 * e.cv_error:12.4g}" if math.isfinite(e.cv_error) else f"{'diverged':>12}"
            se = f"{100 * e.cv_se:7.2g}" if math.isfinite(e.cv_se) else f"{'':>7}"
            rows.append(
                f"{'*' if e.chosen else ' '} {e.n_terms:5d}  {e.log_evidence:12.6g}  {e.objective:10.6g}  "
                f"{cv}   {se}   {e.source + (', screened' if e.screened else ''):<14}  {structure}"
            )
        if self.rule:
            rows.append(f"(* chosen: {self.rule})")
        return "\n".join(rows)

    def to_json(self) -> dict:
        return {"rule": self.rule, "entries": [e.to_json() for e in self.entries]}

    @classmethod
    def from_json(cls, doc: dict) -> ModelPath:
        return cls(tuple(PathEntry.from_json(e) for e in doc.get("entries", [])), str(doc.get("rule", "")))
