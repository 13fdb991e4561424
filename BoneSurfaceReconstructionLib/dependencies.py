"""What the module needs from Slicer: a recent enough Python, BoneUSRecon beside the
module file, and the packages of ``Resources/requirements.txt``.

``import BoneUSRecon`` needs no ``sys.path`` tricks: Slicer appends the folder of every
scripted module it loads from outside its own tree to ``sys.path``, and the
``BoneUSRecon`` package sits in that folder (developer mode: the repository root in
*Additional module paths*; installed extension: CMake copies it beside the module
file). If it is missing, :func:`requireBoneUSRecon` says so in one line.

Third-party packages are installed lazily, when an action first needs them, the Slicer
way: ``slicer.packaging.pip_ensure`` with the requirements file (Slicer 5.11 and later:
it checks, asks the user, installs with progress and offers a restart), else
``slicer.util.pip_install`` per missing requirement after asking. VTK is never
installed.

This file must stay importable by Python 3.9 (Slicer 5.8 and earlier), so that the
module can say which Slicer it needs instead of failing with a SyntaxError.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
import sys
from collections.abc import Callable
from typing import Any

__all__ = [
    "MIN_PYTHON",
    "MIN_SLICER",
    "REQUIREMENTS_FILE",
    "REQUIREMENTS",
    "unsupportedReason",
    "moduleFolder",
    "requireBoneUSRecon",
    "missingRequirements",
    "installRequirements",
]

#: BoneUSRecon needs Python 3.10 (``X | Y`` types, ``zip(strict=True)``). Slicer 5.8
#: and earlier run Python 3.9; Slicer 5.10 and later run Python 3.10+.
MIN_PYTHON = (3, 10)
MIN_SLICER = "5.10"

#: Never installed into Slicer's Python, whatever the requirements file says.
FORBIDDEN = ("vtk", "pyvista", "slicer-core")


def moduleFolder() -> str:
    """The folder holding the module file: where ``BoneUSRecon`` must be found."""
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


#: The module's pip requirements, one per line (read by Slicer's own tools too).
REQUIREMENTS_FILE = os.path.join(moduleFolder(), "Resources", "requirements.txt")


def _requirement_name(req: str) -> str:
    return re.split(r"[\s\[<>=!~;]", req.strip(), maxsplit=1)[0].lower()


#: Import names that differ from the lower-cased distribution name.
_IMPORT_NAMES = {"simpleitk": "SimpleITK"}


def _read_requirements(path: str = REQUIREMENTS_FILE) -> dict[str, str]:
    """``{import name: requirement}`` from the requirements file (comments skipped)."""
    out: dict[str, str] = {}
    if not os.path.isfile(path):  # the module copied without its Resources: said later
        return out
    with open(path, encoding="utf-8") as f:
        for line in f:
            req = line.split("#", 1)[0].strip()
            if req:
                name = _requirement_name(req)
                out[_IMPORT_NAMES.get(name, name.replace("-", "_"))] = req
    return out


#: import name -> pip requirement, from :data:`REQUIREMENTS_FILE`.
REQUIREMENTS = _read_requirements()


def unsupportedReason(version_info: Any = None) -> str | None:
    """Why this Slicer cannot run the module (one sentence), or None if it can.

    Parameters
    ----------
    version_info : sequence of int, optional
        Python's version (default: the running one's ``sys.version_info``).
    """
    v = tuple(sys.version_info if version_info is None else version_info)[:2]
    if v >= MIN_PYTHON:
        return None
    return (
        f"Bone Surface Reconstruction needs Slicer {MIN_SLICER} or later (Python "
        f"{MIN_PYTHON[0]}.{MIN_PYTHON[1]}+); this Slicer runs Python {v[0]}.{v[1]}. "
        "Please install a recent Slicer from https://download.slicer.org."
    )


def requireBoneUSRecon() -> None:
    """Raise a clear error if this Slicer or ``import BoneUSRecon`` cannot work.

    Does not import BoneUSRecon (that would import numpy, scipy... at Slicer startup).

    Raises
    ------
    RuntimeError
        Python too old, or the package is not on ``sys.path`` (normally: not beside
        the module file).
    """
    reason = unsupportedReason()
    if reason:
        raise RuntimeError(reason)
    if importlib.util.find_spec("BoneUSRecon") is None:
        raise RuntimeError(
            f"the BoneUSRecon package was not found: it must sit beside the module file in "
            f"{moduleFolder()} (add the repository root, not a sub-folder, to Additional module paths)"
        )


def missingRequirements() -> list[str]:
    """pip requirements whose import name cannot be found."""
    return [req for name, req in REQUIREMENTS.items() if importlib.util.find_spec(name) is None]


def installRequirements(
    pipInstall: Callable[[str], object] | None = None,
    confirm: Callable[[str], bool] | None = None,
    slicerModule: Any = None,
) -> list[str]:
    """Install the missing requirements (if the user agrees); return what was missing.

    Called before every action that needs the library, so it first checks that
    BoneUSRecon itself can be imported (pip cannot fix that).

    Parameters
    ----------
    pipInstall : callable, optional
        Install one requirement; given, it replaces Slicer's tools (tests).
    confirm : callable, optional
        Asked before ``slicer.util.pip_install``; returning False raises.
        ``pip_ensure`` asks the user itself.
    slicerModule : module, optional
        The ``slicer`` module (default: imported here, only inside Slicer).

    Raises
    ------
    RuntimeError
        Slicer too old, BoneUSRecon not beside the module, the user declined, or a
        requirement is still missing afterwards.
    """
    requireBoneUSRecon()
    if not os.path.isfile(REQUIREMENTS_FILE):
        raise RuntimeError(f"{REQUIREMENTS_FILE}: missing beside the module file")
    missing = missingRequirements()
    if not missing:
        return []
    if any(_requirement_name(req) in FORBIDDEN for req in missing):
        raise RuntimeError(f"refusing to pip-install {missing} into Slicer (Slicer ships VTK)")
    message = (
        "Bone Surface Reconstruction needs these Python packages, which will now be "
        f"installed into Slicer: {', '.join(missing)}. Continue?"
    )
    packaging = None
    if pipInstall is None:
        if slicerModule is None:
            import slicer as slicerModule  # only inside Slicer
        packaging = getattr(slicerModule, "packaging", None)
        if packaging is None or not hasattr(packaging, "pip_ensure"):
            packaging = None
            pipInstall = slicerModule.util.pip_install
    if packaging is not None:  # Slicer 5.11+: its own check, prompt, progress, restart
        packaging.pip_ensure(
            packaging.load_requirements(REQUIREMENTS_FILE), requester="Bone Surface Reconstruction"
        )
    else:
        if confirm is not None and not confirm(message):
            raise RuntimeError(f"missing Python packages: {', '.join(missing)}")
        for req in missing:
            pipInstall(req)
    importlib.invalidate_caches()
    still = missingRequirements()
    if still:
        raise RuntimeError(f"could not install: {', '.join(still)}")
    return missing
