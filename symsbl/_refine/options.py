"""How an output-error refinement runs: its options as one value object, their accepted values as data."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .._base.checks import Constraint, check_params
from .._base.errors import ParameterError, expected
from .noise import MAX_ORDER
from .problem import INTERPOLATIONS

__all__ = ["RefineOptions", "MAX_SAMPLES", "as_options", "requested"]

#: Samples refined on at most (2^18: 8 s at 32768 Hz); longer data contribute evenly spaced windows.
MAX_SAMPLES = 2**18


@dataclass(frozen=True)
class RefineOptions:
    """Options of the output-error refinement (:func:`symsbl.refine`, and ``identify(..., refine=...)``).

    Attributes
    ----------
    select : bool
        Select terms on the output-error evidence (default); False re-estimates the given structure only.
    interpolation : {"cubic", "linear", "periodic", "hold"}
        How the measured inputs run between samples (a cubic spline by default; ``"hold"`` for a digital
        controller's stepped output, ``"periodic"`` for records of whole periods).
    substeps : int or "auto"
        RK4 steps per sample; ``"auto"`` takes enough for the simulation error to stay small over the system's
        memory, at least ``min_substeps``.
    min_substeps : int
        The fewest RK4 steps per sample ``"auto"`` takes (default 1): a caller that knows the inputs drive the
        response faster than the model's own modes say sets it (the hidden-state search does, from the
        input's band).
    smooth : bool
        Fit ``sign(a)`` as a narrow ``tanh`` where a term jumps (the model returned keeps ``sign``).
    max_samples : int
        Samples refined on at most; longer records contribute evenly spaced windows.
    jit : {"auto", True, False}
        Compile the passes with a C compiler when one is available.
    noise : {"auto", "white"} or int
        The noise model of the output error: ``"auto"`` (default) an autoregressive filter per measured channel
        whose order is chosen by BIC on the fitted residual (order 0, white noise, when the residual is white),
        ``"white"``, or a given order (see *A noise model in the likelihood* in the real-records explanation).
    doubts : {"adapt", "report"}
        What a fit does when its residual tests doubt its likelihood (non-white innovations, a noisy measured
        input, a closed loop): ``"adapt"`` (default) refits on short segments, or in a closed loop keeps the
        structure it was given; ``"report"`` fits as usual and only records and warns (for fits whose evidences
        must compare on one likelihood, as the branches of a hidden-state search).

    Examples
    --------
    >>> import symsbl
    >>> options = symsbl.RefineOptions(interpolation="hold")
    >>> options.select, options.interpolation
    (True, 'hold')
    >>> symsbl.RefineOptions(substeps=0).check()
    Traceback (most recent call last):
    ...
    symsbl.ParameterError: substeps: expected an integer >= 1 or 'auto', received 0
    """

    select: bool = True
    interpolation: str = "cubic"
    substeps: int | str = "auto"
    smooth: bool = True
    max_samples: int = MAX_SAMPLES
    jit: object = "auto"
    noise: object = "auto"
    doubts: str = "adapt"
    min_substeps: int = 1

    #: Each option's accepted values (checked by :meth:`check`, where the options enter a computation).
    _constraints: ClassVar[dict] = {
        "select": Constraint.boolean(),
        "interpolation": Constraint.choice(INTERPOLATIONS),
        "substeps": Constraint.integer(low=1, options=("auto",)),
        "smooth": Constraint.boolean(),
        "max_samples": Constraint.integer(low=64),
        "jit": Constraint.choice(("auto", True, False)),
        "noise": Constraint.integer(low=0, high=MAX_ORDER, options=("auto", "white")),
        "doubts": Constraint.choice(("adapt", "report")),
        "min_substeps": Constraint.integer(low=1),
    }

    def check(self) -> RefineOptions:
        """The options with every value checked against its declared constraint."""
        return dataclasses.replace(self, **check_params(dataclasses.asdict(self), self._constraints))

    @classmethod
    def names(cls) -> list[str]:
        """The option names, in declaration order."""
        return [f.name for f in dataclasses.fields(cls)]


def as_options(value, name: str = "refine_options") -> RefineOptions:
    """``value`` (a :class:`RefineOptions`, a dict of its fields, or None for the defaults) as checked options;
    an unknown key is an error naming the valid ones."""
    if value is None:
        return RefineOptions().check()
    if isinstance(value, RefineOptions):
        return value.check()
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        unknown = [k for k in value if k not in RefineOptions.names()]
        if not unknown:
            return RefineOptions(**value).check()
    raise ParameterError(expected(name, f"a RefineOptions or a dict with keys among {RefineOptions.names()}", value))


def requested(refine, refine_options) -> RefineOptions | None:
    """The refinement's options from an identification's ``refine`` (a bool or a :class:`RefineOptions`) and
    ``refine_options`` (a :class:`RefineOptions` or a dict of its fields), checked; None: no refinement."""
    if isinstance(refine, RefineOptions):
        if refine_options is not None:
            raise ParameterError(
                expected(
                    "refine_options",
                    "the refinement's options given once",
                    "both refine=RefineOptions(...) and refine_options",
                    "pass only one",
                    raw=True,
                )
            )
        return as_options(refine, "refine")
    if not isinstance(refine, (bool, np.bool_)):
        raise ParameterError(expected("refine", "True, False or a RefineOptions", refine))
    if not refine:
        return None
    return as_options(refine_options)
