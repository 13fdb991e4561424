"""Checking that BoneUSRecon is importable inside Slicer, and installing its pure-Python needs.

``import BoneUSRecon`` needs no ``sys.path`` tricks: Slicer appends the folder of every
scripted module it loads from outside its own tree to ``sys.path``, and the
``BoneUSRecon`` package sits in that folder in both set-ups:

* Developer mode: the repository root (which holds the module file) is in
  *Additional module paths*, or was selected in the Extension Wizard.
* Installed extension: the extension's CMake copies the package next to the module
  file (``lib/Slicer-X.Y/qt-scripted-modules/BoneUSRecon/``).

If the package is still missing (the module file copied alone somewhere),
:func:`requireBoneUSRecon` says so in one line instead of a bare ``ImportError``.

Third-party needs are installed lazily, from the Apply button's path, with
``slicer.util.pip_install``. VTK is never installed: Slicer ships its own, and a second
VTK in Slicer's Python breaks it; for the same reason pyvista (which depends on vtk) is
not a requirement of the module (only BoneUSRecon's viewer uses it).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
from collections.abc import Callable

__all__ = ["REQUIREMENTS", "moduleFolder", "requireBoneUSRecon", "missingRequirements", "installRequirements"]

#: import name -> pip requirement: every third-party package BoneUSRecon.Logic and the
#: MRML adapter import, except VTK (Slicer's own). numpy comes with Slicer; scipy may
#: not. Testing/test_slicer_mrml.py checks this list against their import statements.
REQUIREMENTS: dict[str, str] = {
    "numpy": "numpy",
    "scipy": "scipy>=1.11",
    # Logic.transform_io writes ITK transform files with it; Slicer ships SimpleITK, so
    # inside Slicer this is found and never installed.
    "SimpleITK": "SimpleITK>=2.3",
}

#: Never installed into Slicer's Python, whatever a requirement pulls in.
FORBIDDEN = ("vtk", "pyvista")


def moduleFolder() -> str:
    """The folder holding the module file: where ``BoneUSRecon`` must be found."""
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def requireBoneUSRecon() -> None:
    """Raise a clear error if ``import BoneUSRecon`` cannot work.

    Does not import BoneUSRecon (that would import numpy, scipy... at Slicer startup).

    Raises
    ------
    RuntimeError
        The package is not on ``sys.path`` (normally: not beside the module file).
    """
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
) -> list[str]:
    """Install the missing requirements (if the user agrees); return what was installed.

    Called before every action that needs the library, so it first checks that
    BoneUSRecon itself is importable (pip cannot fix that).

    Parameters
    ----------
    pipInstall : callable, optional
        ``slicer.util.pip_install`` by default.
    confirm : callable, optional
        Asked with a message before installing; returning False raises.

    Raises
    ------
    RuntimeError
        BoneUSRecon is not beside the module, the user declined, or a requirement is
        still missing afterwards.
    """
    requireBoneUSRecon()
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
