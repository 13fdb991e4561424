"""The Sweep type: geometry helpers in millimetres, validation, and the VTK edge."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonTransforms import vtkTransform

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.sweep import (
    Sweep,
    frame_planes,
    matrix_to_vtk,
    pixel_spacing,
    pixels_to_reference,
    vtk_to_matrix,
)


def pose(rot_deg, spacing, origin):
    m = np.eye(4)
    r = Rotation.from_euler("xyz", rot_deg, degrees=True).as_matrix()
    m[:3, 0] = r[:, 0] * spacing[0]
    m[:3, 1] = r[:, 1] * spacing[1]
    m[:3, 2] = r[:, 2]
    m[:3, 3] = origin
    return m


def make(n=5, h=8, w=12, spacing=(0.1, 0.15)):
    # Frames 2 mm apart along z, parallel, image x along reference x, y along y.
    mats = np.stack([pose((0, 0, 0), spacing, (0, 0, 2.0 * k)) for k in range(n)])
    frames = np.arange(n * h * w, dtype=np.uint8).reshape(n, h, w)
    return Sweep(frames, mats, np.arange(n) * 0.5, np.ones(n, bool))


def test_pixel_spacing_from_column_norms():
    m = pose((10, 20, 30), (0.085, 0.09), (1, 2, 3))
    assert np.allclose(pixel_spacing(m), [0.085, 0.09])
    assert pixel_spacing(np.stack([m, m])).shape == (2, 2)


def test_pixels_to_reference_by_hand():
    m = pose((0, 0, 90), (0.5, 0.25), (10, 20, 30))
    # Rotating 90 degrees about z: image x -> reference +y, image y -> reference -x.
    got = pixels_to_reference(m, np.array([[2.0, 4.0], [0.0, 0.0]]))
    assert np.allclose(got, [[10 - 4 * 0.25, 20 + 2 * 0.5, 30], [10, 20, 30]])


def test_frame_planes():
    s = make()
    origin, axes, normal = frame_planes(s.image_to_reference)
    assert np.allclose(origin[:, 2], np.arange(5) * 2.0)
    assert np.allclose(axes[:, :, 0], [1, 0, 0]) and np.allclose(axes[:, :, 1], [0, 1, 0])
    assert np.allclose(normal, [0, 0, 1])


def test_geometry_in_mm():
    s = make()
    assert np.allclose(s.spacing_mm, [0.1, 0.15])
    assert s.bounds_mm() == pytest.approx([0, 11 * 0.1, 0, 7 * 0.15, 0, 8.0])
    assert s.sweep_length_mm() == pytest.approx(8.0)
    assert s.duration_s() == pytest.approx(2.0)
    assert s.corners_mm().shape == (5, 4, 3)


def test_image_centres_are_the_middle_of_the_corners():
    # An affine pose maps the pixel grid's middle to the mean of its four corners, an
    # independent way to the same point; tilted, scaled frames in arbitrary places.
    rng = np.random.default_rng(3)
    mats = np.stack(
        [pose(rng.uniform(-40, 40, 3), (0.1, 0.15), rng.uniform(-9, 9, 3)) for _ in range(6)]
    )
    s = Sweep(np.zeros((6, 8, 12), np.uint8), mats, np.zeros(6), np.ones(6, bool))
    s = s.replace(valid=np.array([True, False, True, True, False, True]))
    assert np.allclose(s.image_centres(), s.corners_mm().mean(axis=1))
    assert np.allclose(s.image_centres([1, 4]), s.corners_mm(np.array([1, 4])).mean(axis=1))
    c = s.image_centres()
    assert s.sweep_length_mm() == pytest.approx(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())


def test_invalid_frames_are_left_out():
    s = make().replace(valid=np.array([True, True, True, False, False]))
    assert s.n_valid == 3 and s.valid_indices.tolist() == [0, 1, 2]
    assert s.bounds_mm()[5] == pytest.approx(4.0)
    assert s.sweep_length_mm() == pytest.approx(4.0)
    assert s.duration_s() == pytest.approx(1.0)


def test_nan_timestamps_ignored_in_duration():
    s = make().replace(timestamps=np.array([np.nan, 1.0, 2.0, 3.5, np.nan]))
    assert s.duration_s() == pytest.approx(2.5)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(frames=np.zeros((5, 8), np.uint8)), "shape"),
        (
            dict(
                frames=np.zeros((0, 8, 12), np.uint8),
                image_to_reference=np.zeros((0, 4, 4)),
                timestamps=np.zeros(0),
                valid=np.zeros(0, bool),
            ),
            "zero frames",
        ),
        (dict(image_to_reference=np.zeros((4, 4, 4))), "expected 5 4x4 transforms"),
        (dict(timestamps=np.zeros(3)), "expected 5 timestamps"),
        (dict(valid=np.ones(6, bool)), "expected 5 valid flags"),
    ],
)
def test_validation(change, match):
    with pytest.raises(BoneUSReconError, match=match):
        make().replace(**change)


def test_vtk_round_trip():
    s = make()
    images, transforms = s.to_vtk()
    assert isinstance(images[0], vtkImageData) and isinstance(transforms[0], vtkTransform)
    assert images[0].GetDimensions() == (12, 8, 1)
    # VTK point order is x fastest: pixel (i=3, j=2) of frame 1.
    assert images[1].GetScalarComponentAsDouble(3, 2, 0, 0) == s.frames[1, 2, 3]
    back = Sweep.from_vtk(images, transforms, timestamps=s.timestamps)
    assert np.array_equal(back.frames, s.frames)
    assert np.allclose(back.image_to_reference, s.image_to_reference)


def test_from_vtk_folds_image_spacing_into_pose():
    s = make()
    img = vtkImageData()
    img.DeepCopy(s.frame_image(0))
    img.SetSpacing(0.1, 0.15, 1.0)
    img.SetOrigin(5.0, 6.0, 0.0)
    # In mm image units, the transform carries no scale: same geometry as pixels+scale.
    back = Sweep.from_vtk([img], [vtkTransform()])
    assert np.allclose(back.to_reference(0, np.array([[11.0, 7.0]])), [[5 + 1.1, 6 + 1.05, 0]])
    assert np.allclose(back.spacing_mm, [0.1, 0.15])


def test_matrix_vtk_conversions():
    m = pose((1, 2, 3), (0.2, 0.3), (4, 5, 6))
    assert np.allclose(vtk_to_matrix(matrix_to_vtk(m)), m)
    t = vtkTransform()
    t.SetMatrix(matrix_to_vtk(m))
    assert np.allclose(vtk_to_matrix(t), m)
