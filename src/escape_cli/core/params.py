"""Checks of scalar parameters (radii, counts, choices), with one wording; no numpy, so the CLI can use them at start-up.

Each raises `ParameterError` (a usage error, exit code 2 in the CLI):

    "<name> must be a number, got 'abc'"
    "<name> must be at least 1, got 0"
    "<name> must be one of ball, fps, cluster, got 'bogus'"
"""

from __future__ import annotations

import math
import numbers

from escape_cli.errors import ParameterError


def as_number(value, name: str, *, minimum: float | None = None, above: float | None = None,
              maximum: float | None = None) -> float:
    """A finite float within bounds (`minimum` <= v, `above` < v, v <= `maximum`), else ParameterError."""
    if isinstance(value, (bool, str, bytes)) or not isinstance(value, numbers.Real):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ParameterError(f"{name} must be a finite number, got {value!r}")
    if minimum is not None and number < minimum:
        raise ParameterError(f"{name} must be at least {minimum:g}, got {value!r}")
    if above is not None and number <= above:
        raise ParameterError(f"{name} must be greater than {above:g}, got {value!r}")
    if maximum is not None and number > maximum:
        raise ParameterError(f"{name} must be at most {maximum:g}, got {value!r}")
    return number


def as_count(value, name: str, *, minimum: int = 1, maximum: int | None = None) -> int:
    """An integer within [minimum, maximum], else ParameterError (bools are refused)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ParameterError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ParameterError(f"{name} must be at least {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ParameterError(f"{name} must be at most {maximum}, got {value}")
    return int(value)


def as_choice(value, name: str, choices) -> str:
    """One of `choices`, else ParameterError naming them."""
    if value not in choices:
        raise ParameterError(f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}")
    return value
