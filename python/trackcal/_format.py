"""Numbers formatted for people: the shared fixed-point formatter of the reports and the command
line's texts."""

from __future__ import annotations


def fixed(value: float, fmt: str = "{:.3f}") -> str:
    """``fmt.format(value)`` without the sign of a value that rounds to zero: a clock offset of
    -0.004 ms printed "-0.00 ms", which reads as a measured negative offset; the minus survives
    only where a nonzero digit follows it."""
    text = fmt.format(value)
    if text.startswith("-") and "0" in text and not any(c in "123456789" for c in text):  # not -inf
        return text[1:]
    return text
