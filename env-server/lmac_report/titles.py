"""Plot titles that fit their figure: long environment names (`pz:` games with options) and run
paths would otherwise run past the figure's edge and be cut."""
from __future__ import annotations

import textwrap


def fit(title: str, width: int = 60) -> str:
    """`title` broken into lines of at most `width` characters (long words are kept whole)."""
    return "\n".join(textwrap.wrap(title, width=width, break_long_words=False, break_on_hyphens=False)) or title
