"""Slicer Live mode (issue 16 §4), headless on slicer-core's real MRML classes.

The volume node is updated as OpenIGTLinkIF does with each IMAGE message (the pixels
replaced in the observed image data, ``IJKToRAS`` set from the message; or, with
TRANSFORM messages, the matrix of the transform node the image sits under), and the
"event loop" runs the scheduled reads. The model node's final surface must be the
offline reconstruction of the same frames.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonDataModel import vtkImageData

from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.live import LiveParams
from BoneUSRecon.Logic.pipeline import reconstruct
from BoneUSRecon.Logic.sweep import matrix_to_vtk

slicer = pytest.importorskip("slicer")  # the PyPI package slicer-core (test extra)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # Slicer puts the module's folder on sys.path
    sys.path.insert(0, str(ROOT))

from BoneSurfaceReconstructionLib.live import LiveSurface  # noqa: E402


class _Loop:
    """A stand-in for Slicer's event loop: scheduled calls run when it turns."""

    def __init__(self) -> None:
        self.calls: list = []
        self.t = 0.0

    def schedule(self, fn) -> None:
        self.calls.append(fn)

    def turn(self, dt: float) -> None:
        calls, self.calls = self.calls, []
        for fn in calls:
            fn()
        self.t += dt


def _image(h: int, w: int) -> tuple[vtkImageData, np.ndarray]:
    img = vtkImageData()
    img.SetDimensions(w, h, 1)
    arr = np.zeros(h * w, np.uint8)
    vtk_arr = numpy_support.numpy_to_vtk(arr, deep=False)
    img.GetPointData().SetScalars(vtk_arr)
    img._keep = arr  # the VTK array shares this buffer
    return img, arr


def _points(pd) -> np.ndarray:
    return numpy_support.vtk_to_numpy(pd.GetPoints().GetData())


@pytest.mark.parametrize("via", ["image_matrix", "transform_node"])
def test_live_surface_follows_openigtlink_updates(sim_small_corrupted, via):
    sweep = sim_small_corrupted.sweep
    scene = slicer.vtkMRMLScene()
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image_Reference")
    image, buf = _image(sweep.height, sweep.width)
    volume.SetAndObserveImageData(image)
    calibration = None
    if via == "transform_node":
        # PLUS chain: the image in pixels under ProbeToReference, calibration = ImageToProbe
        calibration = np.diag([0.3, 0.3, 1.0, 1.0])
        probe = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ProbeToReference")
        volume.SetAndObserveTransformNodeID(probe.GetID())
    loop = _Loop()
    live = LiveSurface(
        volume,
        calibration=calibration,
        live=LiveParams(update_every_s=0.25),
        schedule=loop.schedule,
        clock=lambda: loop.t,
    )
    live.start()
    shown = []
    for k in range(sweep.n_frames):
        pose = sweep.image_to_reference[k]
        if via == "image_matrix":
            volume.SetIJKToRASMatrix(matrix_to_vtk(pose))
        else:
            probe.SetMatrixTransformToParent(matrix_to_vtk(pose @ np.linalg.inv(calibration)))
        buf[:] = sweep.frames[k].reshape(-1)
        image.GetPointData().GetScalars().Modified()
        image.Modified()
        loop.turn(1 / 30)
        if live.model.GetPolyData() is not None:
            shown.append(live.model.GetPolyData().GetNumberOfPoints())
        if k == 20:  # a pose update alone (tracker faster than video) adds no frame
            if via == "transform_node":
                probe.Modified()
            volume.Modified()
            loop.turn(0.0)
            assert live.frames == 21
    assert live.frames == sweep.n_frames and not live.skipped
    assert len(shown) > 0 and shown[-1] > 0  # the surface was shown while scanning
    final = live.stop()
    assert not live.running
    # The volume node stores IJKToRAS as spacing, directions and origin: the poses come
    # back within 1e-15 mm, not bit for bit, and that can flip a point-dropping decision.
    # So: exactly the offline reconstruction of the poses the scene gave, and within
    # 0.05 mm (mean gold distance) of that of the original sweep.
    poses = live.reconstructor.sweep().image_to_reference
    np.testing.assert_allclose(poses, sweep.image_to_reference, atol=1e-12)
    same = reconstruct(sweep.replace(image_to_reference=poses))
    np.testing.assert_array_equal(_points(final.surface), _points(same.surface))
    offline = reconstruct(sweep)
    model = live.model
    assert model.GetDisplayNode().GetActiveScalarName() == "Distance"
    np.testing.assert_allclose(_points(model.GetPolyData()), _points(final.surface))
    gold = sim_small_corrupted.gold
    assert (
        abs(
            evaluate_surface(model.GetPolyData(), gold).mean
            - evaluate_surface(offline.surface, gold).mean
        )
        < 0.05
    )


def test_live_surface_refuses_bad_nodes_and_frames(sim_small):
    scene = slicer.vtkMRMLScene()
    model = scene.AddNewNodeByClass("vtkMRMLModelNode", "NotAVolume")
    with pytest.raises(ValueError, match="scalar volume"):
        LiveSurface(model)
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Float")
    img = vtkImageData()
    img.SetDimensions(8, 6, 1)
    img.GetPointData().SetScalars(numpy_support.numpy_to_vtk(np.zeros(48, np.float32), deep=True))
    volume.SetAndObserveImageData(img)
    loop = _Loop()
    live = LiveSurface(volume, schedule=loop.schedule, clock=lambda: loop.t)
    live.start()
    img.Modified()
    loop.turn(0.1)
    assert live.frames == 0 and sum(live.skipped.values()) == 1
    assert "8-bit" in next(iter(live.skipped))
    assert live.stop() is None and "0 frames" in live.statusText()


def test_live_surface_takes_the_module_flank_extension(sim_small):
    # The Live panel builds its parameters as Apply does (parameters_from_widget_values of
    # the parameter node): a flank extension reaches the live model, flagged.
    from BoneSurfaceReconstructionLib.parameters import parameters_from_widget_values

    sweep = sim_small.sweep
    params = parameters_from_widget_values({"flankExtension": 1.5})
    scene = slicer.vtkMRMLScene()
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image_Reference")
    image, buf = _image(sweep.height, sweep.width)
    volume.SetAndObserveImageData(image)
    loop = _Loop()
    live = LiveSurface(
        volume,
        params=params,
        live=LiveParams(update_every_s=60.0),  # only the final refit
        schedule=loop.schedule,
        clock=lambda: loop.t,
    )
    live.start()
    for k in range(sweep.n_frames):
        volume.SetIJKToRASMatrix(matrix_to_vtk(sweep.image_to_reference[k]))
        buf[:] = sweep.frames[k].reshape(-1)
        image.GetPointData().GetScalars().Modified()
        image.Modified()
        loop.turn(1 / 30)
    final = live.stop()
    pd = live.model.GetPolyData()
    flag = numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("Extrapolated"))
    assert 0 < flag.sum() < flag.size
    poses = live.reconstructor.sweep().image_to_reference
    same = reconstruct(sweep.replace(image_to_reference=poses), params)
    np.testing.assert_array_equal(_points(final.surface), _points(same.surface))
    np.testing.assert_allclose(_points(pd), _points(same.surface))
