"""Exact money: every number at its shortest decimal form, computed on as a fraction, rounded once to the cent.

Every input number is taken at its shortest decimal form (Python ``repr``, which is what the JSON recording
carries) and computed on as an exact fraction; each money item is rounded once, half-even, to the cent, and every
total is a sum of rounded items. So anyone who reads the recorded numbers re-settles to the cent, with no
dependence on float summation order (docs/market.md, "Exactness and rounding").
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from decimal import Decimal
from fractions import Fraction


def exact(x: float) -> Fraction:
    """The exact value of x's shortest decimal form: 0.1 is 1/10, as written in the recording."""
    return Fraction(repr(float(x)))


def exact_amount(x: object, what: str) -> Fraction:
    """A money amount as a rule returned it (int, float, Fraction or Decimal), exactly; ValueError if it is not a
    finite number."""
    if isinstance(x, bool) or not isinstance(x, (numbers.Rational, float, Decimal)):
        raise ValueError(f"{what} is {x!r}, not a number")
    if isinstance(x, numbers.Rational):
        return Fraction(x)
    if not math.isfinite(x):
        raise ValueError(f"{what} is {x}, not a finite amount")
    return Fraction(x) if isinstance(x, Decimal) else exact(x)


def to_cents(amount: Fraction) -> int:
    """Round an exact amount ($) half-even to whole cents: the only rounding settlement does."""
    return int(round(amount * 100))


def dollars(cents: int) -> Decimal:
    return Decimal(cents).scaleb(-2)


def money_sum(amounts: Iterable[Decimal]) -> Decimal:
    """Exact sum of cent amounts, kept at two places (an empty sum is 0.00)."""
    return sum(amounts, Decimal("0.00"))
