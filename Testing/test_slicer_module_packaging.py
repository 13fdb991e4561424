"""The Slicer module installs and presents itself the Slicer way (issue 12, item 9).

* Supported Slicer versions are stated and checked: the module file and the helpers it
  imports when Slicer loads it parse and import under Python 3.9 grammar (Slicer 5.8
  and earlier), so such a Slicer shows why the module cannot run.
* Dependencies come from ``Resources/requirements.txt``, through
  ``slicer.packaging.pip_ensure`` (Slicer 5.11+) or ``slicer.util.pip_install``.
* The module's Logic reaches the library through ``BoneUSRecon.Logic`` and its own
  ``BoneSurfaceReconstructionLib``, never ``BoneUSRecon.Widgets``.
* The extensions-index entry follows the catalog-entry schema v1.0.0 and agrees with
  CMakeLists.txt; the shipped recording is registered in Sample Data with its SHA256;
  the README's screenshots exist.
"""

from __future__ import annotations

import ast
import hashlib
import json
import re
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODULE_FILE = ROOT / "BoneSurfaceReconstruction.py"
LIB = ROOT / "BoneSurfaceReconstructionLib"
if str(ROOT) not in sys.path:  # Slicer puts the module's folder on sys.path
    sys.path.insert(0, str(ROOT))

from BoneSurfaceReconstructionLib import dependencies, sampledata  # noqa: E402

# Loaded by Slicer at start-up: must be valid Python 3.9.
LOADED_AT_STARTUP = [
    MODULE_FILE,
    LIB / "__init__.py",
    LIB / "dependencies.py",
    LIB / "parameters.py",
]


# -- supported versions ----------------------------------------------------------------
@pytest.mark.parametrize("path", LOADED_AT_STARTUP, ids=lambda p: p.name)
def test_startup_files_are_python_3_9(path: Path) -> None:
    source = path.read_text(encoding="utf-8")
    tree = ast.parse(source, feature_version=(3, 9))  # grammar: no match, no (with ...)
    future = "from __future__ import annotations" in source
    for node in ast.walk(tree):
        # zip(strict=...) and other 3.10 keywords fail at run time on 3.9.
        if isinstance(node, ast.Call) and any(k.arg == "strict" for k in node.keywords):
            pytest.fail(f"{path.name}:{node.lineno}: strict= needs Python 3.10")
        if future:
            continue
        # Without postponed annotations, X | Y in an annotation is evaluated (TypeError on 3.9).
        annotations = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args.args + node.args.kwonlyargs + node.args.posonlyargs
            annotations = [a.annotation for a in args] + [node.returns]
        elif isinstance(node, ast.AnnAssign):
            annotations = [node.annotation]
        for ann in filter(None, annotations):
            for sub in ast.walk(ann):
                if isinstance(sub, ast.BinOp) and isinstance(sub.op, ast.BitOr):
                    pytest.fail(f"{path.name}:{sub.lineno}: 'X | Y' annotation needs Python 3.10")


def test_old_slicer_gets_a_clear_reason() -> None:
    reason = dependencies.unsupportedReason((3, 9, 10))
    assert reason and "Slicer 5.10 or later" in reason and "Python 3.9" in reason
    assert dependencies.unsupportedReason((3, 10, 0)) is None
    assert dependencies.unsupportedReason() is None  # this interpreter
    # The module file uses it: a panel with the reason, its self-test says it too.
    source = MODULE_FILE.read_text()
    assert "_UNSUPPORTED = dependencies.unsupportedReason()" in source
    assert source.count("if _UNSUPPORTED") >= 3


def test_requireBoneUSRecon_refuses_an_old_python(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(dependencies, "unsupportedReason", lambda v=None: "too old")
    with pytest.raises(RuntimeError, match="too old"):
        dependencies.installRequirements(pipInstall=print)


# -- dependencies ------------------------------------------------------------------------
def test_requirements_file_is_the_list_installed() -> None:
    lines = [
        ln.split("#")[0].strip()
        for ln in (ROOT / "Resources" / "requirements.txt").read_text().splitlines()
    ]
    reqs = [ln for ln in lines if ln]
    assert sorted(dependencies.REQUIREMENTS.values()) == sorted(reqs)
    names = {re.split(r"[<>=!~\[; ]", r)[0].lower() for r in reqs}
    assert "numpy" in names and "scipy" in names
    assert not names & {"vtk", "pyvista", "slicer-core"}  # Slicer ships its own VTK


def _fake_slicer(with_packaging: bool, log: list) -> types.SimpleNamespace:
    util = types.SimpleNamespace(pip_install=lambda req: log.append(("pip_install", req)))
    fake = types.SimpleNamespace(util=util)
    if with_packaging:
        fake.packaging = types.SimpleNamespace(
            load_requirements=lambda path: log.append(("load_requirements", path)) or ["REQS"],
            pip_ensure=lambda reqs, requester: log.append(("pip_ensure", reqs, requester)),
        )
    return fake


@pytest.mark.parametrize("with_packaging", [True, False], ids=["pip_ensure", "pip_install"])
def test_missing_requirements_installed_the_slicer_way(
    monkeypatch: pytest.MonkeyPatch, with_packaging: bool
) -> None:
    monkeypatch.setitem(dependencies.REQUIREMENTS, "bone_us_recon_absent_pkg", "absent-pkg>=1")
    log: list = []
    with pytest.raises(RuntimeError, match="could not install: absent-pkg>=1"):
        dependencies.installRequirements(
            confirm=lambda msg: True, slicerModule=_fake_slicer(with_packaging, log)
        )
    if with_packaging:  # Slicer 5.11+: its own prompt, from the requirements file
        assert log == [
            ("load_requirements", dependencies.REQUIREMENTS_FILE),
            ("pip_ensure", ["REQS"], "Bone Surface Reconstruction"),
        ]
    else:  # older Slicer: the missing requirement only, after asking
        assert log == [("pip_install", "absent-pkg>=1")]
        log.clear()
        with pytest.raises(RuntimeError, match="missing Python packages"):
            dependencies.installRequirements(
                confirm=lambda msg: False, slicerModule=_fake_slicer(False, log)
            )
        assert log == []  # declined: nothing installed


def test_nothing_missing_nothing_installed() -> None:
    log: list = []
    assert dependencies.installRequirements(slicerModule=_fake_slicer(True, log)) == []
    assert log == []


# -- Logic through Logic ----------------------------------------------------------------
def test_module_never_imports_widgets() -> None:
    for path in [MODULE_FILE, *LIB.glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            bad = [n for n in names if n.startswith("BoneUSRecon.Widgets")]
            assert not bad, f"{path.name}:{node.lineno} imports {bad}"
    assert not (ROOT / "BoneUSRecon" / "Widgets" / "mrml.py").exists()


# -- extensions index, sample data, screenshots ------------------------------------------
def _cmake_var(name: str) -> str:
    m = re.search(rf'set\({name} "([^"]*)"\)', (ROOT / "CMakeLists.txt").read_text())
    assert m, name
    return m.group(1)


def test_extensions_index_entry_follows_the_catalog_schema() -> None:
    entry = json.loads((ROOT / "SlicerExtensionsIndex" / "BoneUSRecon.json").read_text())
    # Catalog-entry schema v1.0.0: required $schema, category, scm_url; typed optionals.
    assert entry["$schema"] == (
        "https://raw.githubusercontent.com/Slicer/Slicer/main/Schemas/"
        "slicer-extension-catalog-entry-schema-v1.0.0.json#"
    )
    types_ = {
        "category": str,
        "scm_url": str,
        "scm_revision": str,
        "scm_type": str,
        "build_dependencies": list,
        "build_subdirectory": str,
        "enabled": bool,
    }
    for key, value in entry.items():
        if key != "$schema":
            assert isinstance(value, types_[key]), key
    assert entry.get("scm_type", "git") in ("git", "local")
    assert all(isinstance(d, str) for d in entry["build_dependencies"])
    # It agrees with the extension's CMakeLists.txt.
    assert entry["category"] == _cmake_var("EXTENSION_CATEGORY")
    home = _cmake_var("EXTENSION_HOMEPAGE").split("#")[0]
    assert entry["scm_url"].removesuffix(".git") == home
    assert entry["build_dependencies"] == [] and _cmake_var("EXTENSION_DEPENDS") == "NA"
    assert entry["build_subdirectory"] == "."


def test_sample_data_registered_with_the_file_checksum() -> None:
    path = sampledata.samplePath()
    assert path == ROOT / "Resources" / "SampleData" / "BoneUltrasound_L14.igs.mha"
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert digest == sampledata.SHA256
    assert digest in (ROOT / "Resources" / "SampleData" / "README.md").read_text()
    calls: list[dict] = []
    logic = types.SimpleNamespace(registerCustomSampleDataSource=lambda **kw: calls.append(kw))
    sampledata.registerSampleData(logic)
    (kw,) = calls
    assert kw["checksums"] == f"SHA256:{digest}"
    assert kw["uris"] == path.as_uri() and kw["fileNames"] == path.name
    assert kw["loadFileType"] == "SequenceFile" and Path(kw["thumbnailFileName"]).is_file()
    # The module registers it once Slicer has started; CMake installs the file with it.
    assert '"startupCompleted()", _registerSampleData' in MODULE_FILE.read_text()
    cmake = (ROOT / "CMakeLists.txt").read_text()
    for needed in (
        "Resources/SampleData/BoneUltrasound_L14.igs.mha",
        "Resources/requirements.txt",
        "Lib/sampledata.py",
        "Lib/mrml.py",
        "Lib/mrml_sweep.py",
        "Lib/mrml_display.py",
    ):
        assert needed in cmake, needed


def test_screenshots_exist_and_are_shown() -> None:
    shots = sorted((ROOT / "docs" / "images").glob("*.png"))
    assert len(shots) >= 3
    readme = (ROOT / "README.md").read_text() + (ROOT / "docs" / "slicer.md").read_text()
    urls = _cmake_var("EXTENSION_SCREENSHOTURLS")
    for shot in shots:
        assert f"images/{shot.name}" in readme, shot.name
        assert f"docs/images/{shot.name}" in urls, shot.name
        assert 10_000 < shot.stat().st_size < 400_000
