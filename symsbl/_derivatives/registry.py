"""Numerical differentiation strategies: the regression target of x' = D(x) beta.

Every strategy is a *linear operator pair*. ``targets`` applies it to the sampled states to
estimate (an operator applied to) their derivative; ``reduce`` applies the same operator to any
sampled columns, in particular to the dictionary. For pointwise differences ``reduce`` is the
identity. For the weak (integral) form it integrates each column against a smooth test function,
so the equation ``L x' = L D(x) beta`` holds exactly for any linear ``L``, and the noisy state is
never differentiated: ``int phi x' dt = -int phi' x dt``.

Strategies
----------
``PointDifference``   the paper's forward difference, first order.
``CentralDifference`` second order.
``SavitzkyGolay``     local polynomial fit; order = ``polyorder``.
``WeakForm``          integration against compactly supported bumps on windows apart (or overlapping,
                      with the rows whitened).

By default the weak form uses windows that do not overlap, so the measurement noise entering one row
is independent of every other row: the RVM's white-noise evidence stays valid without a correction.
(Overlapping windows or filtering only the target colour the noise, which is what makes a sparse
learner admit spurious terms; ``WeakForm(overlap=2)`` whitens the rows of half-overlapping windows
for the target's noise.)

References
----------
R. Fuentes, N. Dervilis, K. Worden, E.J. Cross (2019), J. Phys.: Conf. Ser. 1264 012050, Sec. 3-4.
D.A. Messenger, D.M. Bortz (2021), Weak SINDy, Multiscale Model. Simul. 19(3).
"""

from __future__ import annotations

from .._base.errors import ParameterError, expected
from .differences import CentralDifference, PointDifference, SavitzkyGolay
from .differentiator import Differentiator
from .weakform import WeakForm

__all__ = ["DIFFERENTIATORS", "get_differentiator"]


#: Differentiation strategies by name (``symsbl identify --derivative``).
DIFFERENTIATORS: dict[str, type] = {
    "weak": WeakForm,
    "central": CentralDifference,
    "point": PointDifference,
    "savgol": SavitzkyGolay,
}


def get_differentiator(spec: str | Differentiator) -> Differentiator:
    """Resolve a differentiator from its registry name or return an instance unchanged.

    Parameters
    ----------
    spec : str or Differentiator
        One of :data:`DIFFERENTIATORS` (``"weak"``, ``"central"``, ``"point"``, ``"savgol"``) or
        an instance of a :class:`Differentiator` subclass.
    """
    if isinstance(spec, str):
        if spec in DIFFERENTIATORS:
            return DIFFERENTIATORS[spec]()
        raise ParameterError(expected("derivative", f"one of {list(DIFFERENTIATORS)}", spec))
    if isinstance(spec, Differentiator):
        return spec
    raise ParameterError(
        expected(
            "derivative", f"one of {list(DIFFERENTIATORS)} or a Differentiator instance", type(spec).__name__, raw=True
        )
    )
