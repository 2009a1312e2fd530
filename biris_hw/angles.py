"""Binary degrees: 4096 counts per revolution, positive counter-clockwise seen from above.

This is also where a number a user hands the API is first looked at, so the checks every numeric
argument shares live here (:func:`exact_real`): a caller may pass any real number type -- any
``numbers.Real``: Python's ``int``, ``float`` and ``Fraction``, numpy's scalars -- and gets the
same answer for the same value, and a :class:`~biris_hw.errors.RequestError` naming the argument
for anything else. Conversions are exact (rational arithmetic), so neither a huge finite value
such as ``10**400`` or ``1e308`` nor a numpy ``longdouble`` beyond a float's range can overflow on
the way to a clamp: they clamp like any other value beyond the limit.

``decimal.Decimal`` is not a ``numbers.Real`` and is refused: a few characters of Decimal
(``Decimal("1e999999999")``) are a number whose exact value no memory holds.
"""

from __future__ import annotations

import numbers
import reprlib
from fractions import Fraction
from typing import SupportsFloat, TypeAlias

from biris_hw.errors import RequestError
from regs.hctl1000 import COUNTS_PER_REV, MOTION_LIMIT_COUNTS

__all__ = [
    "MOTION_LIMIT_COUNTS",
    "RealLike",
    "clamp_counts",
    "counts_to_deg",
    "deg_to_counts",
    "destination_counts",
    "exact_real",
    "is_real",
    "shown",
]

RealLike: TypeAlias = SupportsFloat
"""What the API's numeric arguments are annotated with, so that ``int``, ``float``, ``Fraction``
and numpy's scalars all pass a type checker. At run time :func:`is_real` decides."""


_SHORT = reprlib.Repr()
_SHORT.maxlong = 24
_SHORT.maxstring = 40
_SHORT.maxother = 40


def shown(value: object) -> str:
    """``repr(value)`` cut short, for error messages: one that quotes ``10**400`` in full is
    four hundred digits of noise around the one word that matters."""
    return _SHORT.repr(value)


def is_real(value: object) -> bool:
    """True for a real number of any type (a ``numbers.Real``, which numpy's scalars register
    as), False for bools: ``True`` is an int to Python, but a ``single_scan(True)`` is a
    mistake, not one degree."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def exact_real(value: object, what: str) -> Fraction:
    """``value`` exactly, as a Fraction, if it is a finite real number of any type.

    Exact, so that no value is rounded or overflows before the caller clamps or range-checks
    it: ``10**400`` and ``np.longdouble("1e4000")`` are merely large.

    Args:
        value: the caller's number.
        what: the argument's name, for the error message.

    Returns:
        The value as a :class:`~fractions.Fraction`.

    Raises:
        RequestError: ``value`` is not a real number (a bool, None, a string, a complex, a
            Decimal, an array), or it is NaN or infinite. The message starts with ``what``.
    """
    if not is_real(value):
        raise RequestError(f"{what}: must be a real number, not {type(value).__name__}")
    try:
        if isinstance(value, numbers.Integral):  # int and numpy integers: no float on the way
            return Fraction(int(value))
        if isinstance(value, numbers.Rational):
            return Fraction(int(value.numerator), int(value.denominator))
        ratio = getattr(value, "as_integer_ratio", None)  # float and numpy floats: exact
        if ratio is not None:
            numerator, denominator = ratio()
            return Fraction(numerator, denominator)
        return Fraction(float(value))  # type: ignore[arg-type]  # any other numbers.Real
    except (ArithmeticError, ValueError, TypeError):  # NaN, infinities (and odd types' own)
        raise RequestError(f"{what}: must be finite, not {shown(value)}") from None


def _to_counts(deg: Fraction) -> int:
    """Nearest count (halves to even, as ``round`` does) for an exact angle."""
    return round(deg * COUNTS_PER_REV / 360)


def deg_to_counts(deg: RealLike) -> int:
    """Nearest whole count for ``deg`` degrees, exactly, for any real number type.

    Not clamped: ``deg_to_counts(720)`` is 8192. See :func:`destination_counts` for what a
    motion request uses.

    Raises:
        RequestError: (a ValueError) for NaN, infinities and non-numbers.
    """
    return _to_counts(exact_real(deg, "an angle"))


def destination_counts(deg: object, what: str) -> int:
    """A motion request's angle in counts, clamped by _Scan_limit to +-0x1000 (+-360 degrees).

    What the client API sends: any finite real number is accepted and clamped, however large,
    so ``1e308`` or ``10**400`` degrees is +0x1000 counts.

    Args:
        deg: the angle in degrees.
        what: the argument's name, for the error message.

    Raises:
        RequestError: ``deg`` is not a finite real number; the message starts with ``what``.
    """
    return clamp_counts(_to_counts(exact_real(deg, what)))


def counts_to_deg(counts: float) -> float:
    """Degrees for ``counts`` binary-degree counts."""
    return counts * 360.0 / COUNTS_PER_REV


def clamp_counts(counts: int) -> int:
    """The report's _Scan_limit: truncate a destination to +-0x1000 counts (+-360 degrees)."""
    return max(-MOTION_LIMIT_COUNTS, min(MOTION_LIMIT_COUNTS, counts))
