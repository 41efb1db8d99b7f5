"""The model file: :class:`~symsbl._model.IdentifiedModel` as JSON, written safely and read as data.

A model file travels between people, so reading one must never run code. Every field is checked
against the schema below before anything is built; term texts are parsed by the whitelist
grammar of :mod:`symsbl._symbolic.parse` (never ``eval`` or ``sympify``); numbers must be finite numbers
(not strings, not booleans) that a float holds, wherever they are (an integer of more digits is never
converted); the covariance must be square, symmetric and of the equation's
size; ``version`` must be one this release reads. The ``rhs`` text of each equation, written for
people and for other tools, is read too and must equal the sum of its terms (it is a redundant
copy: an edited ``rhs`` with unchanged ``terms`` is reported, not silently ignored).

Schema (version 2; version 1 files, without ``fit``, are read unchanged)::

    {"format": "symsbl-model", "version": 2, "states": [...], "inputs": [...],
     "fit": "equation-error" | "output-error", "kinematics": {"x": "v", ...}, "measured": [...],
     "outputs": [{"name": str, "kind": "state" | "acceleration" | "algebraic", "of": str (acceleration)}, ...]
                (only when a channel is not a state as it is; else the measured states are the outputs),
     "latent": {"z": "how its scale is fixed", ...} (written for people; derived on reading),
     "covariance": [[...]] (output error: the joint covariance of all coefficients),
     "equations": [{"lhs": str, "rhs": str, "fixed": bool (a kinematic equation),
                    "algebraic": true (only for the equation of an algebraic output, after the states'),
                    "terms": [{"term": str, "coef": float, "std": float|null, "alpha": float|null,
                               "evidence": float|null, "alternatives": [str, ...],
                               "fixed": true (only for a coefficient fixed by convention)}, ...],
                    "noise_std": float, "log_evidence": float|null, "n_rows": int,
                    "covariance": [[float, ...], ...]}, ...],
     "metadata": {...}}
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from .._base.errors import DataError, ExpressionError, expected
from .._base.outputs import safe_output, write_atomic
from .._symbolic.library import MAX_FILE_NODES, MAX_FILE_TERMS, bound_size, expression_nodes
from .._symbolic.parse import parse_expression
from .._symbolic.symbols import symbols as make_symbols
from .estimates import Equation, TermEstimate
from .outputs import AlgebraicOutput, check_outputs, output_from_json
from .path import PATH_SOURCES, ModelPath

__all__ = [
    "JSON_VERSION",
    "READABLE_VERSIONS",
    "MAX_MODEL_TERMS",
    "MAX_MODEL_NODES",
    "model_to_json",
    "model_from_json",
    "save_model",
    "load_model",
]

#: The version this release writes.
JSON_VERSION = 2
#: The versions this release reads.
READABLE_VERSIONS = (1, 2)
#: Most terms, and most expression nodes of their terms, a model file may hold: those of any file of terms.
MAX_MODEL_TERMS, MAX_MODEL_NODES = MAX_FILE_TERMS, MAX_FILE_NODES
#: Fitting methods a model file may name.
FITS = ("equation-error", "output-error")
_WHERE = "model JSON"
#: Most digits of an integer a float holds (below 1.8e308); a longer one is never converted to ``int``.
_FLOAT_DIGITS = 309


def _finite_or_none(x: float):
    return float(x) if np.isfinite(x) else None


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


def model_to_json(model) -> dict[str, Any]:
    """The JSON document of ``model`` (a dict of plain Python values)."""
    equations = []
    for eq in model.equations:
        equations.append(
            {
                "lhs": eq.lhs,
                "rhs": str(eq.rhs_sympy()),
                "fixed": eq.fixed,
                **({"algebraic": True} if eq.algebraic else {}),
                "terms": [
                    {
                        "term": t.name,
                        "coef": t.coef,
                        "std": _finite_or_none(t.std),
                        "alpha": _finite_or_none(t.alpha),
                        "evidence": _finite_or_none(t.evidence),
                        "alternatives": list(t.alternatives),
                        **({"fixed": True} if t.fixed else {}),
                    }
                    for t in eq.terms
                ],
                "noise_std": _finite_or_none(math.sqrt(eq.noise_var)) if np.isfinite(eq.noise_var) else None,
                "log_evidence": _finite_or_none(eq.log_evidence),
                "n_rows": eq.n_rows,
                "covariance": np.asarray(eq.covariance).tolist(),
            }
        )
    doc = {
        "format": "symsbl-model",
        "version": JSON_VERSION,
        "states": list(model.state_names),
        "inputs": list(model.input_names),
        "fit": model.fit.value,
        "kinematics": {x: v for x, v in model.kinematics},
        "measured": list(model.measured_names),
        **({"outputs": [o.to_json() for o in model.outputs]} if any(o.kind != "state" for o in model.outputs) else {}),
        "latent": {name: model.convention(name) for name in model.latent_names},
        "equations": equations,
        "metadata": _jsonable(model.metadata),
    }
    if model.joint_covariance is not None:
        doc["covariance"] = np.asarray(model.joint_covariance).tolist()
    if len(model.path):
        doc["path"] = model.path.to_json()
    return doc


def save_model(model, path) -> None:
    """Write ``model`` as JSON to ``path`` as :func:`symsbl._base.outputs.write_atomic` does (a file through a
    temporary file renamed into place, a link's target likewise, a FIFO or a device written through)."""
    path = safe_output(path, what="path")
    text = json.dumps(model_to_json(model), indent=2) + "\n"
    write_atomic(path, lambda fh: fh.write(text), binary=False)


# ------------------------------------------------------------------------------------------ reading


class _LongInteger:
    """An integer of the JSON text with more digits than a float holds, kept as its length: ``int()`` of a long
    digit string takes time quadratic in its length and is refused past 4300 digits."""

    def __init__(self, digits: int):
        self.digits = digits


def _integer(text: str) -> int | _LongInteger:
    """``json.loads``' ``parse_int``: the integer, or a :class:`_LongInteger` when no float holds it."""
    digits = len(text.lstrip("-"))
    return int(text) if digits <= _FLOAT_DIGITS else _LongInteger(digits)


def _loads(text: str):
    """The JSON document of ``text``, its long integers left unconverted (:func:`_integer`)."""
    return json.loads(text, parse_int=_integer)


def _digits(n: int) -> int:
    """Decimal digits of ``n``, without ``str()`` (refused past 4300 digits)."""
    n = abs(n)
    low = int((n.bit_length() - 1) * math.log10(2)) + 1 if n else 1  # exact or one short
    return low + (n >= 10**low)


def _too_large(value) -> int | None:
    """The digits of ``value`` if it is an integer no float holds, else None."""
    if isinstance(value, _LongInteger):
        return value.digits
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            float(value)
        except OverflowError:
            return _digits(value)
    return None


def _check_numbers(doc) -> None:
    """Every number of ``doc``, at any depth, is one a float holds; the first that is not is named by its path."""
    stack = [(doc, _WHERE)]
    while stack:
        value, where = stack.pop()
        items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
        inner = []
        for key, item in items:
            path = f"{where}.{key}" if isinstance(value, dict) else f"{where}[{key}]"
            if isinstance(item, (dict, list)):
                inner.append((item, path))
            elif (digits := _too_large(item)) is not None:
                raise DataError(
                    expected(
                        path,
                        f"a number within a float's range (magnitude below {sys.float_info.max:.2g})",
                        f"an integer of {digits} digits",
                        "correct the number; a model file holds the floats symsbl wrote",
                        raw=True,
                    )
                )
        stack.extend(reversed(inner))


def _field(doc: dict, key: str, where: str, kind, *, default=..., what: str = ""):
    if key not in doc:
        if default is ...:
            raise DataError(expected(f"{where}", f"a field {key!r}", f"fields {sorted(doc)}", raw=True))
        return default
    value = doc[key]
    if kind == "number":
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok and not (value is None and default is None):
            raise DataError(expected(f"{where}.{key}", what or "a finite number", value))
        return None if value is None else float(value)
    if not isinstance(value, kind):
        names = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
        raise DataError(expected(f"{where}.{key}", what or f"a JSON {names}", value))
    return value


def _names(doc: dict, key: str, default=...) -> tuple[str, ...]:
    names = _field(doc, key, _WHERE, list, default=default, what="a list of names")
    for n in names:
        if not isinstance(n, str):
            raise DataError(expected(f"{_WHERE}.{key}", "names (strings)", n))
    return tuple(names)


def _header(doc) -> tuple[tuple[str, ...], tuple[str, ...], list]:
    if not isinstance(doc, dict):
        raise DataError(
            expected(_WHERE, "a JSON object written by `symsbl identify --json`", type(doc).__name__, raw=True)
        )
    if doc.get("format", "symsbl-model") != "symsbl-model":
        raise DataError(expected(f"{_WHERE}.format", "'symsbl-model'", doc.get("format")))
    version = doc.get("version", 1)
    if isinstance(version, bool) or version not in READABLE_VERSIONS:
        raise DataError(
            expected(
                f"{_WHERE}.version",
                f"one of {list(READABLE_VERSIONS)}",
                version,
                "the file was written by a newer symsbl; upgrade to read it",
            )
        )
    fit = doc.get("fit", "equation-error")
    if fit not in FITS:
        raise DataError(expected(f"{_WHERE}.fit", f"one of {list(FITS)}", fit))
    states, inputs = _names(doc, "states"), _names(doc, "inputs", default=[])
    try:
        make_symbols(list(states) + list(inputs))
    except Exception as err:  # noqa: BLE001 - re-worded with the file's context
        raise DataError(f"{_WHERE}.states and inputs: {str(err).split(': ', 1)[-1]}") from None  # str(err)
    if not states:
        raise DataError(expected(f"{_WHERE}.states", "at least one state name", [], raw=False))
    equations = _field(doc, "equations", _WHERE, list)
    return states, inputs, equations


def _term(raw, where: str, cas: dict, term_cls):
    if not isinstance(raw, dict):
        raise DataError(expected(where, "a JSON object with 'term' and 'coef'", type(raw).__name__, raw=True))
    text = _field(raw, "term", where, str)
    try:
        expr = parse_expression(text, cas, where=f"{where}.term")
    except ExpressionError as err:
        raise DataError(str(err)) from None
    alternatives = _field(raw, "alternatives", where, list, default=[])
    if not all(isinstance(a, str) for a in alternatives):
        raise DataError(expected(f"{where}.alternatives", "a list of term names (strings)", alternatives))
    std = _field(raw, "std", where, "number", default=None, what="a finite number >= 0 or null")
    alpha = _field(raw, "alpha", where, "number", default=None, what="a finite number > 0 or null")
    if std is not None and std < 0:
        raise DataError(expected(f"{where}.std", "a finite number >= 0 or null", std))
    if alpha is not None and alpha <= 0:
        raise DataError(expected(f"{where}.alpha", "a finite number > 0 or null", alpha))
    evidence = _field(raw, "evidence", where, "number", default=None, what="a finite number or null")
    fixed = _field(raw, "fixed", where, bool, default=False, what="true or false")
    return term_cls(
        expr=expr,
        coef=_field(raw, "coef", where, "number"),
        std=math.nan if std is None else std,
        alpha=math.nan if alpha is None else alpha,
        evidence=math.nan if evidence is None else evidence,
        alternatives=tuple(alternatives),
        fixed=fixed,
    )


def _covariance(raw: dict, where: str, terms) -> np.ndarray:
    cov = raw.get("covariance")
    n = len(terms)
    if cov is None:
        return np.diag([0.0 if not math.isfinite(t.std) else t.std**2 for t in terms])
    try:
        arr = np.array(cov, dtype=float)
    except (TypeError, ValueError):
        raise DataError(
            expected(f"{where}.covariance", f"a {n} x {n} array of numbers", "non-numeric entries", raw=True)
        ) from None
    if arr.size == 0 and n == 0:
        return np.zeros((0, 0))
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)):
        got = f"shape {arr.shape}" if arr.shape != (n, n) else "non-finite entries"
        raise DataError(expected(f"{where}.covariance", f"a finite {n} x {n} array (one row per term)", got, raw=True))
    if not _symmetric(arr) or np.any(np.diag(arr) < 0):
        raise DataError(
            expected(
                f"{where}.covariance", "a symmetric matrix with a non-negative diagonal", "one that is not", raw=True
            )
        )
    return arr


def _check_rhs(raw: dict, where: str, cas: dict, terms) -> None:
    """The optional ``rhs`` text must equal the sum of the terms (at fixed probe points)."""
    if "rhs" not in raw:
        return
    text = _field(raw, "rhs", where, str)
    try:
        rhs = parse_expression(text, cas, where=f"{where}.rhs")
    except ExpressionError as err:
        raise DataError(str(err)) from None
    total = sum((t.coef * t.expr for t in terms), ca.SX(0))
    variables = list(cas.values())
    f = ca.Function(
        "rhs_check",
        [ca.vertcat(*variables)],
        [rhs, total, sum((abs(t.coef) * ca.fabs(t.expr) for t in terms), ca.SX(0))],
    )
    rng = np.random.default_rng(7)
    # probes of either sign, then positive ones: a term such as sqrt(h) is defined for h > 0 only, where
    # both sides must agree; outside a term's domain both sides must be undefined alike
    for k in range(16):
        z = rng.uniform(0.2, 2.0, len(variables)) * (rng.choice([-1.0, 1.0], len(variables)) if k < 8 else 1.0)
        a, b, scale = (float(v) for v in f(z))
        if not math.isfinite(a) and not math.isfinite(b):
            continue
        if not (math.isfinite(a) and math.isfinite(b)) or abs(a - b) > 1e-9 * max(scale, 1e-300):
            raise DataError(
                expected(
                    f"{where}.rhs",
                    "the sum of the equation's terms",
                    repr(text)[:80],
                    "edit 'terms' (the source of truth) and delete or regenerate 'rhs'",
                    raw=True,
                )
            )


def _equation(raw, where: str, states, cas: dict, seen: list, algebraic=()):
    if not isinstance(raw, dict):
        raise DataError(expected(where, "a JSON object", type(raw).__name__, raw=True))
    lhs = _field(raw, "lhs", where, str)
    is_algebraic = _field(raw, "algebraic", where, bool, default=False, what="true or false")
    if lhs not in (algebraic if is_algebraic else states) or lhs in seen:
        what = (
            f"one equation per algebraic output {list(algebraic)}"
            if is_algebraic
            else f"one equation per state {list(states)}"
        )
        raise DataError(expected(f"{where}.lhs", what, lhs))
    seen.append(lhs)
    raw_terms = _field(raw, "terms", where, list)
    terms = [_term(rt, f"{where}.terms[{i}]", cas, TermEstimate) for i, rt in enumerate(raw_terms)]
    _check_rhs(raw, where, cas, terms)
    noise_std = _field(raw, "noise_std", where, "number", default=None, what="a finite number >= 0")
    if noise_std is not None and noise_std < 0:
        raise DataError(expected(f"{where}.noise_std", "a finite number >= 0", noise_std))
    log_evidence = _field(raw, "log_evidence", where, "number", default=None, what="a finite number or null")
    n_rows = raw.get("n_rows", 0)
    if isinstance(n_rows, bool) or not isinstance(n_rows, int) or n_rows < 0:
        raise DataError(expected(f"{where}.n_rows", "an integer >= 0", n_rows))
    fixed = _field(raw, "fixed", where, bool, default=False, what="true or false")
    return Equation(
        lhs=lhs,
        terms=tuple(terms),
        covariance=_covariance(raw, where, terms),
        noise_var=math.nan if noise_std is None else noise_std**2,
        log_evidence=math.nan if log_evidence is None else log_evidence,
        n_rows=n_rows,
        fixed=fixed,
        algebraic=is_algebraic,
    )


def _kinematics(doc, states) -> tuple:
    pairs = _field(doc, "kinematics", _WHERE, dict, default={}, what="an object {position: velocity}")
    for x, v in pairs.items():
        if x not in states or not isinstance(v, str) or v not in states or v == x:
            raise DataError(
                expected(f"{_WHERE}.kinematics", f"position: velocity pairs of the states {list(states)}", {x: v})
            )
    return tuple(pairs.items())


def _measured(doc, states, outputs) -> tuple | None:
    measured = _field(doc, "measured", _WHERE, list, default=None, what="a list of state names")
    if measured is not None and ((not measured and not outputs) or any(m not in states for m in measured)):
        raise DataError(expected(f"{_WHERE}.measured", f"names among the states {list(states)}", measured))
    return None if measured is None else tuple(measured)


#: Most outputs a model file may declare.
MAX_OUTPUTS = 1000


def _outputs(doc) -> tuple:
    """The outputs a model file declares (none: its measured states are its outputs), read as data."""
    raw = _field(doc, "outputs", _WHERE, list, default=[], what="a list of outputs")
    if len(raw) > MAX_OUTPUTS:
        raise DataError(expected(f"{_WHERE}.outputs", f"at most {MAX_OUTPUTS} outputs", len(raw)))
    return tuple(output_from_json(o, f"{_WHERE}.outputs[{k}]") for k, o in enumerate(raw))


def _symmetric(arr: np.ndarray) -> bool:
    """Symmetric to rounding: entries equal to 1e-6 of themselves or of the matrix's largest entry."""
    return bool(np.allclose(arr, arr.T, rtol=1e-6, atol=1e-6 * float(np.abs(arr).max(initial=0.0))))


def _joint_covariance(doc, n: int) -> np.ndarray | None:
    if "covariance" not in doc:
        return None
    try:
        arr = np.array(doc["covariance"], dtype=float)
    except (TypeError, ValueError):
        raise DataError(
            expected(f"{_WHERE}.covariance", f"a {n} x {n} array of numbers", "non-numeric entries", raw=True)
        ) from None
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)) or not _symmetric(arr):
        raise DataError(
            expected(
                f"{_WHERE}.covariance",
                f"a finite symmetric {n} x {n} array (one row per coefficient)",
                f"shape {arr.shape}",
                raw=True,
            )
        )
    return arr


def _bounded(count: int, most: int, what: str) -> None:
    """Refuse a model file asking for more work than any identification gives: re-simulating it costs time and
    memory in proportion to its terms and their expressions."""
    bound_size(
        count,
        most,
        what,
        where=f"{_WHERE}.equations",
        why="the most a model of this release is re-simulated with",
        fix="a model file holds the terms an identification kept; check where this one came from",
        error=DataError,
    )


def _path(doc) -> ModelPath:
    """The model path of a file (optional), every field checked as data."""
    raw = doc.get("path")
    if raw is None:
        return ModelPath()
    where = f"{_WHERE}.path"
    ok = isinstance(raw, dict) and isinstance(raw.get("entries", []), list) and isinstance(raw.get("rule", ""), str)
    if ok:
        for e in raw.get("entries", []):
            ok = (
                ok
                and isinstance(e, dict)
                and isinstance(e.get("terms"), dict)
                and all(
                    isinstance(k, str) and isinstance(v, list) and all(isinstance(n, str) for n in v)
                    for k, v in e["terms"].items()
                )
            )
            ok = ok and isinstance(e.get("n_terms"), int) and not isinstance(e.get("n_terms"), bool)
            ok = ok and all(
                k in e and (e[k] is None or (isinstance(e[k], (int, float)) and not isinstance(e[k], bool)))
                for k in ("log_evidence", "objective", "cv_error", "cv_se")
            )
            ok = ok and e.get("source") in PATH_SOURCES and isinstance(e.get("chosen"), bool)
            ok = ok and isinstance(e.get("screened", False), bool)
    if not ok:
        raise DataError(
            expected(
                where,
                "an object {rule, entries: [{terms, n_terms, log_evidence, objective, "
                "cv_error, cv_se, source, chosen[, screened]}]} as symsbl writes it",
                "another layout",
                "delete 'path' (it is optional)",
                raw=True,
            )
        )
    return ModelPath.from_json(raw)


def model_from_json(cls, doc):
    """Rebuild ``cls`` (IdentifiedModel) from a JSON document (dict or string), read as data."""
    if isinstance(doc, str):
        try:
            doc = _loads(doc)
        except (json.JSONDecodeError, RecursionError) as err:
            raise DataError(expected(_WHERE, "valid JSON", f"invalid JSON ({err})", raw=True)) from None
    _check_numbers(doc)
    states, inputs, raw_equations = _header(doc)
    syms = tuple(ca.SX.sym(n) for n in states + inputs)
    cas = {s.name(): s for s in syms}
    outputs = _outputs(doc)
    algebraic = tuple(o.name for o in outputs if isinstance(o, AlgebraicOutput))
    _bounded(
        sum(len(raw["terms"]) for raw in raw_equations if isinstance(raw, dict) and isinstance(raw.get("terms"), list)),
        MAX_MODEL_TERMS,
        "terms",
    )
    seen: list = []
    equations = [
        _equation(raw, f"{_WHERE}.equations[{k}]", states, cas, seen, algebraic) for k, raw in enumerate(raw_equations)
    ]
    _bounded(expression_nodes(t.expr for eq in equations for t in eq.terms), MAX_MODEL_NODES, "expression nodes")
    missing = [s for s in states + algebraic if s not in seen]
    if missing:
        raise DataError(
            expected(
                f"{_WHERE}.equations",
                f"one equation per state {list(states)} and per algebraic output {list(algebraic)}"
                if algebraic
                else f"one equation per state {list(states)}",
                f"none for {missing}",
                raw=True,
            )
        )
    order = {name: i for i, name in enumerate(states + algebraic)}
    equations.sort(key=lambda e: order[e.lhs])
    kinematics = _kinematics(doc, states)
    outputs = check_outputs(outputs, states, algebraic, kinematics, where=f"{_WHERE}.outputs")
    metadata = doc.get("metadata", {})
    if not isinstance(metadata, dict):
        raise DataError(expected(f"{_WHERE}.metadata", "a JSON object", type(metadata).__name__, raw=True))
    n_coefs = sum(len(eq.terms) for eq in equations)
    return cls(
        states=syms[: len(states)],
        inputs=syms[len(states) :],
        equations=tuple(equations),
        metadata=metadata,
        fit=doc.get("fit", "equation-error"),
        kinematics=kinematics,
        measured=_measured(doc, states, outputs),
        joint_covariance=_joint_covariance(doc, n_coefs),
        path=_path(doc),
        outputs=outputs,
    )


def load_model(cls, path):
    """Read a model file; every problem is a one-line :class:`~symsbl.DataError`."""
    path = Path(path)
    if not path.is_file():
        what = "a directory" if path.is_dir() else "no such file"
        raise DataError(expected(f"model file {str(path)!r}", "an existing JSON file", what, raw=True))
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise DataError(expected(f"model file {str(path)!r}", "UTF-8 JSON text", "binary content", raw=True)) from None
    except PermissionError:
        raise DataError(expected(f"model file {str(path)!r}", "a readable file", "no permission", raw=True)) from None
    try:
        doc = _loads(text)
    except (json.JSONDecodeError, RecursionError) as err:
        raise DataError(
            expected(f"model file {str(path)!r}", "valid JSON", f"invalid JSON ({err})"[:160], raw=True)
        ) from None
    return model_from_json(cls, doc)
