"""Why a frame was left out, as a countable key: one place for every summary.

Segmenters and the sweep reader explain each rejected or invalid frame in free text
that often carries the frame's own numbers ("jump of 4.5 mm from neighbouring
frames", "contour too short (0.0 mm)"). Summaries count frames per *kind* of reason,
so :func:`reason_key` strips those numbers (and what is in brackets or after a colon)
the same way for the ``segment`` command, the report and the Slicer module, whatever
wording the rules use now or later. The full text stays with each frame.
"""

from __future__ import annotations

import re
import string
from collections import Counter
from collections.abc import Iterable, Mapping

__all__ = ["reason_key", "count_reasons", "format_reason_counts"]

# A number with an optional unit right after it ("4.5 mm", "12 px", "30%", "1e-3").
_NUMBER = re.compile(
    r"[-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?\s*(?:(?:mm|px|deg|ms|s|x)\b|%)?", re.IGNORECASE
)
# A linking word left without its number ("jump of  from ..."): dropped.
_DANGLING = re.compile(r"\b(?:of|by|at|to|is|was|=)\s+(?=(?:from|to|at|in|of|by|and|or)\b|$)")


#: What a key neither starts nor ends with: punctuation and any whitespace (a carriage
#: return or a tab before a separator left the separator leading the key).
_SEPARATORS = string.whitespace + ",.-:;#"


def reason_key(reason: object) -> str:
    """The kind of a reason: without numbers, bracketed details or text after a colon.

    Parameters
    ----------
    reason : object
        A frame's reason (any text; ``None`` or empty gives ``"unspecified"``).

    Returns
    -------
    str
        A short key, the same for every frame rejected by the same rule.

    Examples
    --------
    >>> reason_key("jump of 4.5 mm from neighbouring frames")
    'jump from neighbouring frames'
    >>> reason_key("contour too short after dropping off-neighbour points (0.0 mm)")
    'contour too short after dropping off-neighbour points'
    >>> reason_key("no bone found: contrast 0.12")
    'no bone found'
    >>> reason_key("only 2 slices with a bone contour")
    'only slices with a bone contour'
    >>> reason_key(None), reason_key("  ")
    ('unspecified', 'unspecified')
    >>> reason_key(": odd: text"), reason_key("odd")
    ('odd', 'odd')
    """
    text = "" if reason is None else str(reason)
    text = re.sub(r"\([^)]*\)|\[[^\]]*\]", " ", text)  # bracketed details
    # Leading separators first, so that the key of a key is the key itself.
    text = text.lstrip(_SEPARATORS)
    head = re.split(r"[:;]", text, maxsplit=1)[0]
    text = head if head.strip() else text
    text = _NUMBER.sub(" ", text)
    text = " ".join(text.split())
    for _ in range(3):  # "... of by ..." can need more than one pass
        text = " ".join(_DANGLING.sub(" ", text).split())
    text = text.strip(_SEPARATORS)
    return text or "unspecified"


def count_reasons(reasons: Iterable[object] | Mapping[object, object]) -> dict[str, int]:
    """``{reason_key: number of frames}``, most frequent first.

    Parameters
    ----------
    reasons : iterable of str, or mapping ``{frame: reason}``
    """
    values = reasons.values() if isinstance(reasons, Mapping) else reasons
    counts = Counter(reason_key(r) for r in values)
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def format_reason_counts(counts: Mapping[str, int]) -> str:
    """One line such as ``"no bone found: 3; jump from neighbouring frames: 2"``."""
    items = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
    return "; ".join(f"{reason_key(k)}: {n}" for k, n in items)
