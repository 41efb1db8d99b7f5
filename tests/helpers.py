"""Helpers shared by the tests."""

import re


def exactly(message: str) -> str:
    """A ``pytest.raises(match=...)`` pattern that matches ``message`` and nothing else."""
    return "^" + re.escape(message) + "$"


def chain(masses, springs, zeta: float, kg: float, kc: float):
    """Masses in a chain, spring ``i`` (and a dashpot of ``zeta`` of its critical damping on mass ``i``) tying mass
    ``i`` to mass ``i - 1`` (the ground for ``i = 1``), a cubic spring ``kg`` to the ground and ``kc`` between the
    last two masses, the force ``F`` on the last: the system and its states ``x``, ``v`` (lists)."""
    import numpy as np

    from symsbl import OdeSystem, symbols

    n = len(masses)
    m, k = np.asarray(masses, dtype=float), np.asarray(springs, dtype=float)
    c = 2 * zeta * np.sqrt(k * m)
    x = list(symbols(" ".join(f"x{i + 1}" for i in range(n))))
    v = list(symbols(" ".join(f"v{i + 1}" for i in range(n))))
    (F,) = symbols("F")
    stretch = [x[0]] + [x[i] - x[i - 1] for i in range(1, n)]
    rate = [v[0]] + [v[i] - v[i - 1] for i in range(1, n)]
    force = [k[i] * stretch[i] + c[i] * rate[i] for i in range(n)]
    force[0] += kg * x[0] ** 3
    force[-1] += kc * stretch[-1] ** 3
    accel = [((force[i + 1] if i + 1 < n else F) - force[i]) / m[i] for i in range(n)]
    return OdeSystem(tuple(x + v), (F,), tuple(v + accel), name=f"chain of {n}"), x, v
