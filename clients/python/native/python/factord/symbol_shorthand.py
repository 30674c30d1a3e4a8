"""GTSAM's ``symbol_shorthand``: ``X(1) == symbol('x', 1)``, one function per letter, so that
``from factord.symbol_shorthand import X, L`` works as with GTSAM."""

from ._native import symbol as _symbol


def _shorthand(letter):
    def make(index):
        return _symbol(letter, index)

    make.__name__ = letter.upper()
    make.__qualname__ = letter.upper()
    make.__doc__ = f"symbol('{letter}', index)"
    return make


for _letter in "abcdefghijklmnopqrstuvwxyz":
    globals()[_letter.upper()] = _shorthand(_letter)
del _letter
