"""The docstring examples of chosen modules run, so they stay true.

Not ``--doctest-modules`` over the package: that would import every module (the
Widgets need a display for some), and some examples elsewhere are illustrations, not
checks. Add a module here once its examples run quickly on their own.
"""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "BoneUSRecon.Logic.errors",
    "BoneUSRecon.Logic.fileio",
    "BoneUSRecon.Logic.intensity",
    "BoneUSRecon.Logic.poses",
    "BoneUSRecon.Logic.progress",
    "BoneUSRecon.Logic.reasons",
    "BoneUSRecon.Logic.segmentation.track_incremental",
    "BoneUSRecon.Logic.sweep",
    "BoneUSRecon.cli.common",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name: str) -> None:
    module = importlib.import_module(name)
    result = doctest.testmod(
        module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False
    )
    assert result.attempted > 0, f"{name} has no examples: remove it from MODULES"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
