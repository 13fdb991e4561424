"""Bone points in the live path: a :class:`LiveReconstructor` built with the user's points
follows them as the batch segmenter does, judges them against the frames received so
far (a point the probe has not reached is no fault during the scan, a point off the whole
scan a warning at the end), and the ``live`` and ``table`` commands take ``--bone-point``.
Distances are in mm against the simulator's analytic bones (:mod:`two_bones`)."""

from __future__ import annotations

import json
import threading
import types

import numpy as np
import pytest
from two_bones import bone_top, forearm, neighbour_top, off_centre, on_bones

from BoneUSRecon.cli import main
from BoneUSRecon.cli.igtl import SweepServer
from BoneUSRecon.cli.live import SessionResult
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.live import LiveReconstructor
from BoneUSRecon.Logic.pipeline import params_with
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import write_simulation
from BoneUSRecon.Logic.sweep import frame_planes


def _live(points, along: int = 4) -> LiveReconstructor:
    return LiveReconstructor(params_with(along=along, bone_points=points))


def _feed(live: LiveReconstructor, sweep, frames=None) -> None:
    for k, image in sweep.iter_frames(frames):
        live.add_frame(image, sweep.image_to_reference[k], sweep.timestamps[k])


def _past_the_end(sweep, mm: float = 40.0) -> np.ndarray:
    """A point ``mm`` along the sweep past its last frame's plane."""
    origin, _, normal = frame_planes(sweep.image_to_reference)
    ahead = np.sign(normal[-1] @ (origin[-1] - origin[0]))
    return origin[-1] + mm * ahead * normal[-1]


@pytest.mark.parametrize("seed", [2, 3])  # as test_bone_point.py's off-centre seeds
def test_a_live_session_follows_a_point_on_the_off_centre_bone(seed):
    # The ulna swept near the image's edge, the radius near the middle: without a point
    # the live track takes the radius (as offline), with one on the ulna the ulna, at
    # every refit from the first, and the final contours are the offline ones.
    sim = forearm("hard", seed, width=224)
    sw, shift = off_centre(sim)
    plain = _live([])
    _feed(plain, sw)
    bone, nb, _ = on_bones(sim, sw, plain.refit(final=True).segmentation)
    assert nb <= 1.0 and bone >= 8.0, (bone, nb)  # on the radius (test_bone_point.py)
    point = bone_top(sim, sw, 6, shift)
    live = _live([point])
    for k, image in sw.iter_frames():
        live.add_frame(image, sw.image_to_reference[k], sw.timestamps[k])
        if k >= 8:  # 2 x 4 control points' frames: the live refits from here on
            bone, nb, _ = on_bones(sim, sw, live.refit().segmentation)
            assert bone <= 0.3 and nb >= 8.0, (k, bone, nb)
    final = live.refit(final=True)
    bone, nb, n = on_bones(sim, sw, final.segmentation)
    assert bone <= 0.3 and nb >= 8.0 and n >= 8, (bone, nb, n)
    assert final.summary["warnings"] == [] and final.summary["bone_points"]
    offline = segment_sweep(sw, params_with(bone_points=[point]).segmentation)
    assert [c.frame for c in final.segmentation.accepted] == [c.frame for c in offline.accepted]
    for a, b in zip(final.segmentation.accepted, offline.accepted, strict=True):
        np.testing.assert_array_equal(a.points_px, b.points_px)


def test_frames_keep_their_pixels_until_the_probe_reaches_the_point():
    # A point on the off-centre ulna in frame 9 of 12: the refit at frame 8 follows the
    # radius (the lane rule; the point not reached) and the track then moves to the
    # ulna. The frames the move leaves off the track are searched as offline: every
    # frame kept its pixels meanwhile (dropping them cost 2 of 9 frames here).
    sim = forearm("hard", 2, width=224)
    sw, shift = off_centre(sim)
    point = bone_top(sim, sw, 9, shift)
    live = _live([point])
    _feed(live, sw, np.arange(8))
    early = live.refit()
    bone, nb, _ = on_bones(sim, sw, early.segmentation)
    assert nb <= 1.0 and bone >= 8.0 and early.summary["warnings"] == [], (bone, nb)
    assert live.pixels_kept == 8
    for k in range(8, 12):
        _feed(live, sw, np.array([k]))
        live.refit()
    final = live.refit(final=True)
    assert live.recovery_counts["no_pixels"] == 0
    bone, nb, n = on_bones(sim, sw, final.segmentation)
    assert bone <= 0.3 and nb >= 8.0 and n >= 9, (bone, nb, n)
    offline = segment_sweep(sw, params_with(bone_points=[point]).segmentation)
    assert [c.frame for c in final.segmentation.accepted] == [c.frame for c in offline.accepted]
    assert live.pixels_kept < 12  # reached: the track frames gave theirs up


def test_a_point_the_probe_has_not_reached_is_no_fault_until_the_end():
    # A point on the radius in frame 10 of 12 (22 mm from frame 7's plane): with frames
    # 0-7 in, a refit follows the ulna (the default) and says nothing of the point; the
    # final refit at that moment says it is not on the scan (the batch error's sentence);
    # once the probe passes it the track follows the radius and the warning is gone.
    sim = forearm("standard", 1)
    sw = sim.sweep
    point = neighbour_top(sim, sw, 10)
    live = _live([point], along=3)
    _feed(live, sw, np.arange(8))
    early = live.refit()
    bone, nb, _ = on_bones(sim, sw, early.segmentation)
    assert bone <= 0.3 and nb >= 8.0 and early.summary["warnings"] == []
    ended = live.refit(final=True).summary["warnings"]
    assert len(ended) == 1, ended
    assert ended[0].startswith("bone point 1 (") and "from the nearest frame's plane" in ended[0]
    assert ended[0].endswith("it is not on this sweep")
    with pytest.raises(BoneUSReconError) as batch:  # offline, the same sentence refuses it
        segment_sweep(
            sw.replace(
                frames=sw.frames[:8],
                image_to_reference=sw.image_to_reference[:8],
                timestamps=sw.timestamps[:8],
                valid=sw.valid[:8],
            ),
            params_with(bone_points=[point]).segmentation,
        )
    assert batch.value.message == ended[0]
    _feed(live, sw, np.arange(8, 12))
    final = live.refit(final=True)
    bone, nb, n = on_bones(sim, sw, final.segmentation)
    assert nb <= 0.3 and bone >= 8.0 and n >= 10, (bone, nb, n)
    assert final.summary["warnings"] == []


def test_a_point_off_the_whole_scan_is_a_warning_at_the_end():
    sim = forearm("standard", 1)
    sw = sim.sweep
    past = _past_the_end(sw)
    live = _live([neighbour_top(sim, sw, 6), past])  # point 2 off the scan
    _feed(live, sw)
    assert live.refit().summary["warnings"] == []  # during the scan: not reached yet
    final = live.refit(final=True)
    warnings = final.summary["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith("bone point 2 (")
    assert "40.0 mm from the nearest frame's plane" in warnings[0]
    assert final.segmentation.warnings == tuple(warnings)
    assert SessionResult(final=final).warnings == tuple(warnings)  # the CLI's session
    assert SessionResult().warnings == ()
    # Point 1 still rules: the track on the radius.
    bone, nb, n = on_bones(sim, sw, final.segmentation)
    assert nb <= 0.3 and bone >= 8.0 and n >= 10, (bone, nb, n)


def test_a_point_no_contour_reaches_is_warned_as_offline():
    # Half way between the two bones' tops, in the tissue: the frames reach it, no
    # contour does. The live warning is the batch one, at each refit and the final.
    sim = forearm("standard", 1)
    sw = sim.sweep
    between = 0.5 * (bone_top(sim, sw, 6) + neighbour_top(sim, sw, 6))
    live = _live([between])
    _feed(live, sw)
    offline = segment_sweep(sw, params_with(bone_points=[between]).segmentation)
    assert len(offline.warnings) == 1 and "no accepted contour within 3 mm" in offline.warnings[0]
    for r in (live.refit(), live.refit(final=True)):
        assert r.summary["warnings"] == list(offline.warnings)
        assert r.segmentation.warnings == offline.warnings
    bone, _, n = on_bones(sim, sw, live.refit(final=True).segmentation)
    assert bone <= 0.3 and n >= 10  # the track as without the point


# -- the Slicer panel's parameters (no Qt needed) -------------------------------------------


def test_the_slicer_live_panel_takes_the_bone_point_list():
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[1])
    if root not in sys.path:  # Slicer puts the module's folder on sys.path
        sys.path.insert(0, root)
    from BoneSurfaceReconstructionLib.live import liveParameters
    from BoneSurfaceReconstructionLib.parameters import (
        CHOICE_PARAMETERS,
        FLOAT_PARAMETERS,
        INT_PARAMETERS,
    )

    class _Markups:  # the two calls bone_points_from_node makes of a point list
        def GetNumberOfControlPoints(self) -> int:
            return 1

        def GetNthControlPointPositionWorld(self, k: int, xyz: list) -> None:
            xyz[:] = [1.0, 2.0, 3.0]

    names = (*CHOICE_PARAMETERS, *INT_PARAMETERS, *FLOAT_PARAMETERS)
    node = types.SimpleNamespace(**dict.fromkeys(names), bonePoints=None)  # library defaults
    node.controlPointsU = 6
    assert liveParameters(node).segmentation.rejection.bone_points == ()
    node.bonePoints = _Markups()
    params = liveParameters(node)
    assert params.segmentation.rejection.bone_points == ((1.0, 2.0, 3.0),)
    assert params.fit.n_control_points[0] == 6


# -- the command line ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def forearm_files(tmp_path_factory) -> dict:
    # 32 frames: ``table`` reconstructs with the default 15 control points first.
    sim = forearm("standard", 1, n_frames=32)
    return write_simulation(sim, tmp_path_factory.mktemp("live_bone_point"))


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = int(exc.code)
    got = capsys.readouterr()
    return code, got.out, got.err


def test_cli_live_takes_bone_points_and_warns_of_one_off_the_scan(tmp_path, capsys):
    sim = forearm("standard", 1)
    sw = sim.sweep
    on_radius, past = neighbour_top(sim, sw, 6), _past_the_end(sw)
    server = SweepServer(sw, "127.0.0.1", 0, fps=100.0)
    thread = threading.Thread(target=server.serve, daemon=True)
    thread.start()
    out = tmp_path / "s.vtp"
    argv = ["live", "--port", str(server.port), "-o", str(out), "--along", "4"]
    argv += ["--update-every", "0.3", "--reconnect", "0.3", "--json", "-q"]
    for p in (on_radius, past):
        argv += ["--bone-point", *(f"{v:.4f}" for v in p)]
    try:
        code, stdout, stderr = _run(argv, capsys)
    finally:
        server.stop()
        thread.join(timeout=5)
    assert code == 0, stderr
    doc = json.loads(stdout)
    warnings = doc["summary"]["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith("bone point 2 (")
    assert warnings[0].endswith("it is not on this sweep")
    assert stderr.strip().splitlines() == [f"bone-us-recon: warning: {warnings[0]}"]
    assert doc["summary"]["bone_points"] == [
        pytest.approx(list(on_radius), abs=1e-3),
        pytest.approx(list(past), abs=1e-3),
    ]
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from BoneUSRecon.Logic.vtkio import read_polydata

    surface = vtk_to_numpy(read_polydata(out).GetPoints().GetData())
    assert np.median(sim.neighbour.distance(surface)) <= 0.5  # the radius's surface


@pytest.mark.parametrize(
    ("command", "values", "problem"),
    [
        ("live", ["1", "2", "nan"], "'nan' is not a finite number of mm"),
        ("live", ["1", "2", "inf"], "'inf' is not a finite number of mm"),
        ("live", ["1", "2"], "expected 3 arguments"),
        ("table", ["1", "2", "x"], "'x' is not a finite number of mm"),
        ("table", ["1", "2", "1e999"], "'1e999' is not a finite number of mm"),
        ("table", ["1", "2"], "expected 3 arguments"),
        ("table", ["0", "0", "-500"], "it is not on this sweep"),
    ],
)
def test_cli_live_and_table_refuse_bad_bone_points(
    forearm_files, tmp_path, capsys, command, values, problem
):
    if command == "live":
        argv = ["live", "--port", "1", "-o", str(tmp_path / "s.vtp")]
    else:
        argv = ["table", str(forearm_files["sweep"]), "--gold", str(forearm_files["gold"])]
        argv += ["--along", "4", "--plot", str(tmp_path / "t.png")]
    code, _, err = _run([*argv, "-q", "--bone-point", *values], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("bone-us-recon")
    assert "--bone-point" in lines[0] or "bone point 1" in lines[0]
    assert problem in lines[0], lines[0]
    assert list(tmp_path.iterdir()) == []


def test_cli_table_follows_the_point_and_warns(forearm_files, capsys):
    sim = forearm("standard", 1, n_frames=32)
    sw = sim.sweep
    argv = ["table", str(forearm_files["sweep"]), "--gold", str(forearm_files["gold"])]
    argv += ["--along", "5", "10", "--json", "-q"]
    code, out, err = _run(argv, capsys)
    assert code == 0 and err == "", err
    plain = json.loads(out)["mean_distance_mm"]
    # On the radius: the surface is the radius's, far from the ulna's gold points.
    pointed = argv + ["--bone-point", *(f"{v:.4f}" for v in neighbour_top(sim, sw, 16))]
    code, out, err = _run(pointed, capsys)
    assert code == 0 and err == "", err
    doc = json.loads(out)
    assert doc["warnings"] == [] and min(doc["mean_distance_mm"]) > 5 * max(plain)
    # Between the bones: the default track, and the batch warning on stderr and in JSON.
    between = 0.5 * (bone_top(sim, sw, 16) + neighbour_top(sim, sw, 16))
    code, out, err = _run(argv + ["--bone-point", *(f"{v:.4f}" for v in between)], capsys)
    assert code == 0
    doc = json.loads(out)
    assert doc["mean_distance_mm"] == pytest.approx(plain)
    assert len(doc["warnings"]) == 1 and "no accepted contour within 3 mm" in doc["warnings"][0]
    assert err.strip().splitlines() == [f"bone-us-recon: warning: {doc['warnings'][0]}"]
