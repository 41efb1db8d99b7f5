"""Helpers shared by the tests."""

import re


def exactly(message: str) -> str:
    """A ``pytest.raises(match=...)`` pattern that matches ``message`` and nothing else."""
    return "^" + re.escape(message) + "$"
