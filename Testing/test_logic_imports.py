"""BoneUSRecon.Logic stays pure: importing it never loads Slicer, Qt or VTK rendering.

Each check runs in a fresh interpreter (subprocess), because this pytest process has
long since imported pyvista and slicer for other tests.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Packages that must not appear in sys.modules (nor any of their submodules) after
# importing Logic, and raw name prefixes (VTK's rendering module families).
FORBIDDEN_PACKAGES = (
    "slicer",
    "slicer_core",
    "qt",
    "ctk",
    "PySide2",
    "PySide6",
    "PyQt5",
    "PyQt6",
    "pyvista",
    "matplotlib.pyplot",
)
FORBIDDEN_PREFIXES = ("vtkmodules.vtkRendering", "vtkmodules.vtkInteraction", "vtkmodules.vtkViews")

_PROBE = textwrap.dedent(
    """
    import importlib, json, pkgutil, sys
    sys.path.insert(0, {root!r})
    targets = {targets!r}
    imported = []
    for name in targets:
        pkg = importlib.import_module(name)
        imported.append(name)
        if hasattr(pkg, "__path__"):  # a package: import every submodule too
            for info in pkgutil.walk_packages(pkg.__path__, prefix=name + "."):
                importlib.import_module(info.name)
                imported.append(info.name)
    print(json.dumps({{"imported": imported, "modules": sorted(sys.modules)}}))
    """
)


def _import_in_fresh_interpreter(*targets: str) -> tuple[list[str], list[str]]:
    code = _PROBE.format(root=str(ROOT), targets=list(targets))
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    return out["imported"], out["modules"]


def _forbidden(modules: list[str]) -> list[str]:
    return [
        m
        for m in modules
        if m.startswith(FORBIDDEN_PREFIXES)
        or any(m == p or m.startswith(p + ".") for p in FORBIDDEN_PACKAGES)
    ]


def test_forbidden_detector_catches_rendering_and_slicer() -> None:
    # The check below must be able to fail: feed it what a leak looks like.
    leaked = ["vtkmodules.vtkRenderingCore", "slicer", "slicer.util", "PyQt5.QtCore", "pyvista"]
    assert _forbidden(leaked) == leaked
    assert _forbidden(["vtkmodules.vtkCommonCore", "qtpy_not_really", "numpy", "slicerx"]) == []


def test_logic_and_all_submodules_import_without_slicer_qt_or_rendering() -> None:
    imported, modules = _import_in_fresh_interpreter("BoneUSRecon.Logic")
    # Walked the whole package (not just __init__): the stages are all there.
    for stage in ("sequence_io", "sweep", "vtkio", "resampling", "bspline"):
        assert f"BoneUSRecon.Logic.{stage}" in imported
    assert _forbidden(modules) == [], "BoneUSRecon.Logic loaded Slicer/Qt/rendering modules"


def test_mrml_adapter_imports_without_slicer() -> None:
    # The adapter imports slicer lazily (only to reach the Sequences logic), so the
    # library, its CLI and its docs can import it on machines without Slicer.
    _, modules = _import_in_fresh_interpreter("BoneSurfaceReconstructionLib.mrml")
    assert not [m for m in modules if m == "slicer" or m.startswith(("slicer.", "slicer_core"))]
    assert not [m for m in modules if m.startswith("vtkmodules.vtkRendering")]


@pytest.mark.parametrize("lib", ["dependencies", "parameters", "selftest", "mrml", "sampledata"])
def test_slicer_module_helpers_import_without_slicer(lib: str) -> None:
    # The module's Lib files must not import slicer at import time (only inside the
    # functions that need the application), so Slicer can load them before the scene.
    code = (
        # The module's folder (the repository root) on sys.path, as Slicer puts it.
        f"import sys; sys.path.insert(0, {str(ROOT)!r})\n"
        f"import BoneSurfaceReconstructionLib.{lib}\n"
        "print(sorted(m for m in sys.modules if m == 'slicer' or m.startswith(('slicer.', 'qt', 'ctk'))))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "[]"
