"""Making BoneUSRecon importable inside Slicer, and its pure-Python needs installed.

* Installed extension: the extension's CMake copies the ``BoneUSRecon`` package next to
  the module file (``lib/Slicer-X.Y/qt-scripted-modules/BoneUSRecon/``), a folder Slicer
  puts on ``sys.path``: nothing to do.
* Developer mode (the module folder of a source checkout added to *Additional module
  paths*): the package sits one folder up, in the repository root, which is added to
  ``sys.path`` if ``BoneUSRecon`` cannot be imported otherwise.

Third-party needs are installed lazily, from the Apply button's path, with
``slicer.util.pip_install``. VTK is never installed: Slicer ships its own, and a second
VTK in Slicer's Python breaks it; for the same reason pyvista (which depends on vtk) is
not a requirement of the module (only BoneUSRecon's viewer uses it).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable

__all__ = ["REQUIREMENTS", "ensureBoneUSReconImportable", "missingRequirements", "installRequirements"]

#: import name -> pip requirement: every third-party package BoneUSRecon.Logic and the
#: MRML adapter import, except VTK (Slicer's own). numpy comes with Slicer; scipy may
#: not. Testing/test_slicer_mrml.py checks this list against their import statements.
REQUIREMENTS: dict[str, str] = {
    "numpy": "numpy",
    "scipy": "scipy>=1.11",
}

#: Never installed into Slicer's Python, whatever a requirement pulls in.
FORBIDDEN = ("vtk", "pyvista")


def repositoryRoot() -> str:
    """The folder holding both this module's folder and the ``BoneUSRecon`` package."""
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def ensureBoneUSReconImportable() -> str | None:
    """Make ``import BoneUSRecon`` work; return the folder added to ``sys.path``, if any.

    Does not import BoneUSRecon (that would import numpy, scipy... at Slicer startup).
    """
    if importlib.util.find_spec("BoneUSRecon") is not None:
        return None
    root = repositoryRoot()
    if os.path.isfile(os.path.join(root, "BoneUSRecon", "__init__.py")) and root not in sys.path:
        sys.path.insert(0, root)
        importlib.invalidate_caches()
        return root
    return None


def missingRequirements() -> list[str]:
    """pip requirements whose import name cannot be found."""
    return [req for name, req in REQUIREMENTS.items() if importlib.util.find_spec(name) is None]


def installRequirements(
    pipInstall: Callable[[str], object] | None = None,
    confirm: Callable[[str], bool] | None = None,
) -> list[str]:
    """Install the missing requirements (if the user agrees); return what was installed.

    Parameters
    ----------
    pipInstall : callable, optional
        ``slicer.util.pip_install`` by default.
    confirm : callable, optional
        Asked with a message before installing; returning False raises.

    Raises
    ------
    RuntimeError
        The user declined, or a requirement is still missing afterwards.
    """
    missing = missingRequirements()
    if not missing:
        return []
    if any(req.split("[")[0].split(">")[0].split("=")[0].strip().lower() in FORBIDDEN for req in missing):
        raise RuntimeError(f"refusing to pip-install {missing} into Slicer (Slicer ships VTK)")
    if confirm is not None and not confirm(
        "Bone Surface Reconstruction needs these Python packages, which will now be "
        f"installed into Slicer: {', '.join(missing)}. Continue?"
    ):
        raise RuntimeError(f"missing Python packages: {', '.join(missing)}")
    if pipInstall is None:
        import slicer  # only inside Slicer

        pipInstall = slicer.util.pip_install
    for req in missing:
        pipInstall(req)
    importlib.invalidate_caches()
    still = missingRequirements()
    if still:
        raise RuntimeError(f"could not install: {', '.join(still)}")
    return missing
