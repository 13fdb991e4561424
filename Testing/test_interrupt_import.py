"""Ctrl-C that lands inside a VTK import is an interruption, not an internal error
(issue 12, item 6).

VTK's compiled modules turn an exception raised while they import their dependencies
into ``ImportError: Failed to load vtk...``. pyvista imports several of them lazily at
the first render, i.e. in the middle of ``reconstruct --report``, where a Ctrl-C once
gave ``internal error: ImportError: Failed to load vtkRenderingContextOpenGL2``. Each
test runs a fresh interpreter (SIGINT handlers and the import state are per process)
and reproduces the conversion exactly: a real SIGINT is raised during the import of
``vtkRenderingContextOpenGL2`` and the KeyboardInterrupt is replaced by VTK's
ImportError.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from BoneUSRecon.Logic.sequence_io import write_sweep

ROOT = Path(__file__).resolve().parents[1]
MESSAGE = "bone-us-recon: interrupted; no output was written"

# Make the first import of vtkRenderingContextOpenGL2 behave as VTK does when Ctrl-C
# arrives during it: the handler runs (SIGINT), VTK reports ImportError instead.
SHIM = textwrap.dedent(
    """
    import signal, sys

    class _CtrlCInVtkImport:
        # First in sys.meta_path: asked by every import statement and import_module.
        fired = False

        def find_spec(self, name, path=None, target=None):
            if name == "vtkmodules.vtkRenderingContextOpenGL2" and not self.fired:
                self.fired = True
                try:
                    signal.raise_signal(signal.SIGINT)
                except KeyboardInterrupt:
                    raise ImportError("Failed to load vtkRenderingContextOpenGL2") from None
            return None

    import vtkmodules  # puts VTK's own finder first: ours goes in front of it

    sys.meta_path.insert(0, _CtrlCInVtkImport())
    """
)


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.fixture(scope="module")
def sweep_file(sim_small, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_sweep(sim_small.sweep, tmp_path_factory.mktemp("intr") / "s.mha")


def test_run_guarded_reports_an_interrupt_disguised_as_import_error(tmp_path: Path) -> None:
    code = SHIM + textwrap.dedent(
        """
        import argparse
        from BoneUSRecon.cli.common import run_guarded

        def command(args):
            import vtkmodules.vtkRenderingContextOpenGL2  # noqa: F401
            return 0

        raise SystemExit(run_guarded(command, argparse.Namespace(debug=False)))
        """
    )
    proc = _run(code, tmp_path)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip() == MESSAGE
    assert "internal error" not in proc.stderr


def test_a_real_import_error_is_still_an_internal_error(tmp_path: Path) -> None:
    code = textwrap.dedent(
        """
        import argparse
        from BoneUSRecon.cli.common import run_guarded

        def command(args):
            raise ImportError("Failed to load vtkSomething")

        raise SystemExit(run_guarded(command, argparse.Namespace(debug=False)))
        """
    )
    proc = _run(code, tmp_path)
    assert proc.returncode == 1 and "internal error: ImportError" in proc.stderr


def test_reconstruct_report_interrupted_in_a_vtk_import(sweep_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    argv = [
        "reconstruct",
        str(sweep_file),
        "-o",
        str(out / "s.vtp"),
        "--points-out",
        str(out / "p.vtp"),
        "--report",
        str(out / "rep"),
        "-q",
    ]
    code = SHIM + f"from BoneUSRecon.cli import main\nraise SystemExit(main({argv!r}))\n"
    proc = _run(code, tmp_path)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip() == MESSAGE
    assert sorted(os.listdir(out)) == []  # nothing written, no temporary files


def test_reconstruct_report_loads_the_rendering_modules_before_the_work(
    sweep_file: Path, tmp_path: Path
) -> None:
    code = textwrap.dedent(
        f"""
        import sys
        import BoneUSRecon.Logic.pipeline as pipeline
        from BoneUSRecon.cli import main

        real = pipeline.reconstruct

        def spy(*a, **k):
            print("loaded:", "vtkmodules.vtkRenderingContextOpenGL2" in sys.modules,
                  "pyvista" in sys.modules)
            return real(*a, **k)

        pipeline.reconstruct = spy
        raise SystemExit(main(["reconstruct", {str(sweep_file)!r}, "-o", "s.vtp",
                               "--report", "rep", "-q"]))
        """
    )
    proc = _run(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "loaded: True True" in proc.stdout


def test_finalizer_errors_after_ctrl_c_are_silent(monkeypatch, capsys):
    # Ctrl-C can cut an object's construction short (a pyvista Plotter lacking
    # `_initialized`); its __del__ then fails and Python prints "Exception ignored in"
    # with a traceback under the one-line message. After SIGINT those are silenced.
    import gc
    import sys

    from BoneUSRecon.cli.common import _SigintSeen

    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)

    class HalfBuilt:
        def __del__(self) -> None:
            raise AttributeError("'HalfBuilt' object has no attribute '_initialized'")

    handler = _SigintSeen()
    try:
        handler(2, None)
    except KeyboardInterrupt:
        pass
    assert handler.fired
    obj = HalfBuilt()
    del obj
    gc.collect()
    assert "Exception ignored" not in capsys.readouterr().err
