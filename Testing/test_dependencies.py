"""Every runtime dependency in pyproject.toml is imported by the package for a purpose.

Issue 12: a dependency the package never imports (scikit-image was one, ~100 MB) moves
to an extra. The scan reads the import statements of ``BoneUSRecon`` itself.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]

#: Distribution name -> import name, where they differ.
IMPORT_NAMES = {
    "pillow": "PIL",
    "vtk": "vtkmodules",
    "lazy-loader": "lazy_loader",
    "simpleitk": "SimpleITK",
}


def _imported_top_level_names() -> set[str]:
    names: set[str] = set()
    for f in (ROOT / "BoneUSRecon").rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names


def _runtime_dependencies() -> list[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    return [re.split(r"[\s\[<>=!~;]", d, maxsplit=1)[0].lower() for d in project["dependencies"]]


def test_every_runtime_dependency_is_imported_by_the_package() -> None:
    imported = _imported_top_level_names()
    deps = _runtime_dependencies()
    assert "numpy" in deps and "numpy" in imported  # the scan works
    unused = [d for d in deps if IMPORT_NAMES.get(d, d) not in imported]
    assert not unused, f"runtime dependencies the package never imports: {unused}"


def test_scikit_image_is_an_extra_not_a_runtime_dependency() -> None:
    assert "scikit-image" not in _runtime_dependencies()
    assert "skimage" not in _imported_top_level_names()
