"""The observation model: what each measured channel of a record is, ``y = h(x, u, theta)``.

A model's states are not always what a sensor records. Each channel of a record is one :class:`Output` of
the model, an expression of its states, inputs and coefficients with its own noise:

- :class:`StateOutput`: a state itself (a displacement transducer on a position, a vibrometer on a velocity);
- :class:`AccelerationOutput`: the derivative of a velocity state, ``h = f_v(x, u, theta)``, the right-hand side
  of the identified velocity equation (its terms and coefficients enter the output);
- :class:`AlgebraicOutput`: a channel with an equation of its own, ``y = sum_j c_j phi_j(x, u)``, identified
  from the library like a state equation (a force cell, an impedance head).

A new kind of sensor is one more subclass here, registered in :data:`OUTPUT_KINDS`: the refinement, the
validation and the model file ask each output for its expression and nothing else. A state that no output
reads and that belongs to no kinematic pair with a measured member is *latent* (:func:`latent_of`).
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import casadi as ca

from .._base.errors import DataError, expected

__all__ = [
    "Output",
    "StateOutput",
    "AccelerationOutput",
    "AlgebraicOutput",
    "OUTPUT_KINDS",
    "state_outputs",
    "output_from_json",
    "latent_of",
    "check_outputs",
]


@dataclass(frozen=True)
class Output(abc.ABC):
    """One measured channel: the data column ``name`` and how the model predicts it.

    Attributes
    ----------
    name : str
        The column of the records that holds it.

    Examples
    --------
    An accelerometer on a Duffing oscillator: its records hold ``a``, the model's ``v'``:

    >>> import symsbl
    >>> x, v, F = symsbl.symbols("x v F")
    >>> system = symsbl.OdeSystem((x, v), (F,), (v, F - 2 * v - 400 * x - 4e6 * x**3), name="duffing")
    >>> record = symsbl.simulate(system.with_outputs(a=system.rhs[1]), symsbl.time_grid(8.0, 200),
    ...                          inputs=symsbl.Multisine(rms=2.0, f_min=1.0, f_max=10.0, seed=0))
    >>> library = symsbl.polynomial([x, v], 3) + symsbl.inputs([F])
    >>> accelerometer = record.with_states(["a"]).with_noise(0.01, seed=1)   # 1 % noise
    >>> model = symsbl.identify(accelerometer, library, states=["x", "v"], kinematics="x:v:a")
    >>> model.outputs
    (AccelerationOutput(name='a', velocity='v'),)
    >>> sorted(model.equation("v").names)
    ['F', 'v', 'x', 'x**3']
    """

    name: str
    kind: ClassVar[str] = ""

    @abc.abstractmethod
    def expression(self, states: Mapping[str, ca.SX], rows: Mapping[str, ca.SX]) -> ca.SX:
        """The output at the state symbols ``states`` (by name), ``rows`` the right-hand side of every equation
        (by its left-hand side: state equations and algebraic ones) at those states."""

    @property
    def state(self) -> str | None:
        """The state the channel records directly (None: it is an expression)."""
        return None

    @property
    def equation(self) -> str | None:
        """The equation whose right-hand side the channel records (None: none)."""
        return None

    @property
    def observes(self) -> str | None:
        """The state whose kinematic pair the channel measures (a position, velocity or acceleration), if any."""
        return self.state

    def to_json(self) -> dict[str, Any]:
        """The model file's record of this output."""
        return {"name": self.name, "kind": self.kind}


@dataclass(frozen=True)
class StateOutput(Output):
    """A state recorded as it is (``h = x_i``); the column is named like the state.

    Examples
    --------
    >>> import casadi as ca
    >>> x, v = ca.SX.sym("x"), ca.SX.sym("v")
    >>> StateOutput("x").expression({"x": x, "v": v}, {})
    SX(x)
    """

    kind: ClassVar[str] = "state"

    def expression(self, states, rows) -> ca.SX:
        return states[self.name]

    @property
    def state(self) -> str | None:
        return self.name


@dataclass(frozen=True)
class AccelerationOutput(Output):
    """The derivative of the velocity state ``velocity`` (an accelerometer): the right-hand side of its equation.

    Attributes
    ----------
    velocity : str
        The velocity state of a position-velocity pair.

    Examples
    --------
    >>> import casadi as ca
    >>> x, v = ca.SX.sym("x"), ca.SX.sym("v")
    >>> AccelerationOutput("a", "v").expression({"x": x, "v": v}, {"x": v, "v": -2 * x - 0.1 * v})
    SX(((-2*x)-(0.1*v)))
    """

    velocity: str = ""
    kind: ClassVar[str] = "acceleration"

    def expression(self, states, rows) -> ca.SX:
        return rows[self.velocity]

    @property
    def equation(self) -> str | None:
        return self.velocity

    @property
    def observes(self) -> str | None:
        return self.velocity

    def to_json(self) -> dict[str, Any]:
        return {**super().to_json(), "of": self.velocity}


@dataclass(frozen=True)
class AlgebraicOutput(Output):
    """A channel with an equation of its own, ``name = sum_j c_j phi_j(x, u)`` (a force cell): the model's
    equation whose left-hand side is ``name``.

    Examples
    --------
    A force cell between a mass and the ground reads the spring and damper forces, ``Fc = k x + c v``:

    >>> import symsbl
    >>> x, v, F = symsbl.symbols("x v F")
    >>> system = symsbl.OdeSystem((x, v), (F,), (v, F - 2 * v - 400 * x), name="oscillator")
    >>> record = symsbl.simulate(system.with_outputs(Fc=400 * x + 2 * v), symsbl.time_grid(8.0, 200),
    ...                          inputs=symsbl.Multisine(rms=2.0, f_min=1.0, f_max=10.0, seed=0))
    >>> library = symsbl.polynomial([x, v], 2) + symsbl.inputs([F])
    >>> model = symsbl.identify(record.with_noise(0.01, seed=1), library, states=["x", "v"], kinematics="x:v",
    ...                         outputs=["Fc"])
    >>> model.equation("Fc").algebraic, sorted(model.equation("Fc").names)
    (True, ['v', 'x'])
    """

    kind: ClassVar[str] = "algebraic"

    def expression(self, states, rows) -> ca.SX:
        return rows[self.name]

    @property
    def equation(self) -> str | None:
        return self.name


#: The kinds of output, by the name the model file gives them.
OUTPUT_KINDS: dict[str, type[Output]] = {cls.kind: cls for cls in (StateOutput, AccelerationOutput, AlgebraicOutput)}


def state_outputs(names: Sequence[str]) -> tuple[Output, ...]:
    """The outputs of records that hold the states ``names`` as they are."""
    return tuple(StateOutput(n) for n in names)


def latent_of(states: Sequence[str], outputs: Sequence[Output], kinematics) -> tuple[str, ...]:
    """The states no output observes, neither directly nor through the kinematic pair they belong to: latent
    states, whose laws are found with no record of them."""
    observed = {o.observes for o in outputs} - {None}
    pairs = [tuple(p) for p in kinematics]
    for x, v in pairs:
        if x in observed or v in observed:
            observed |= {x, v}
    return tuple(s for s in states if s not in observed)


def check_outputs(
    outputs: Sequence[Output], states: Sequence[str], algebraic: Sequence[str], kinematics, where: str = "outputs"
) -> tuple[Output, ...]:
    """``outputs`` checked against the model: a state output reads a state, an acceleration the velocity of a
    kinematic pair, an algebraic output names an algebraic equation; names are distinct from each other and
    from the other states and inputs."""
    outputs = tuple(outputs)
    velocities = {v for _, v in kinematics}
    names = [o.name for o in outputs]
    for o in outputs:
        if not isinstance(o, Output):
            raise DataError(expected(where, "Output objects", type(o).__name__, raw=True))
        if isinstance(o, StateOutput) and o.name not in states:
            raise DataError(expected(f"{where}: {o.name!r}", f"a state among {list(states)}", o.name, raw=True))
        if isinstance(o, AccelerationOutput) and (o.velocity not in velocities or o.name in states):
            raise DataError(
                expected(
                    f"{where}: {o.name!r}",
                    "the acceleration of the velocity of a position-velocity "
                    f"pair {sorted(velocities)}, named unlike the states",
                    o.velocity,
                    raw=True,
                )
            )
        if isinstance(o, AlgebraicOutput) and (o.name not in algebraic or o.name in states):
            raise DataError(
                expected(
                    f"{where}: {o.name!r}", f"an algebraic equation of the model {list(algebraic)}", o.name, raw=True
                )
            )
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise DataError(expected(where, "one output per column", f"{dupes} more than once", raw=True))
    return outputs


def output_from_json(raw, where: str) -> Output:
    """An output of a model file, read as data."""
    if not isinstance(raw, dict) or not isinstance(raw.get("name"), str) or raw.get("kind") not in OUTPUT_KINDS:
        raise DataError(
            expected(
                where,
                "an object {name, kind} with kind one of " + str(list(OUTPUT_KINDS)),
                raw if not isinstance(raw, dict) else {k: raw[k] for k in list(raw)[:3]},
                raw=False,
            )
        )
    if raw["kind"] == "acceleration":
        if not isinstance(raw.get("of"), str):
            raise DataError(expected(f"{where}.of", "the name of the velocity state", raw.get("of")))
        return AccelerationOutput(raw["name"], raw["of"])
    return OUTPUT_KINDS[raw["kind"]](raw["name"])
