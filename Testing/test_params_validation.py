"""Every parameter class refuses bad values at construction, naming the field and the
value, and coerces good ones to the declared types (issue 13)."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from BoneUSRecon.Logic.bspline import FitParams
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.live import LiveParams
from BoneUSRecon.Logic.params_check import ParameterTypeError
from BoneUSRecon.Logic.pipeline import ReconstructionParams, params_with
from BoneUSRecon.Logic.registration import RegistrationParams
from BoneUSRecon.Logic.resampling import ResamplingParams
from BoneUSRecon.Logic.segmentation import (
    PosteriorParams,
    RecoveryParams,
    RejectionParams,
    SegmentationParams,
    ShadowPathParams,
    SnakeParams,
)
from BoneUSRecon.Logic.simulation import HardParams, ImagingParams, SimulationParams
from BoneUSRecon.Logic.surface import SurfaceParams

#: (class, field, bad value, what the message says after "Class.field ").
BAD = [
    (ShadowPathParams, "shadow_mm", -1, "must be > 0, got -1"),
    (ShadowPathParams, "n_passes", 2.5, "must be an integer, got 2.5"),
    (ShadowPathParams, "phase_symmetry", "False", "must be True or False"),
    (ShadowPathParams, "phase_wavelengths_mm", (0.6, -1.0), "must be > 0"),
    (ShadowPathParams, "fov_fraction", 1.0, r"must lie in \[0, 1\), got 1.0"),
    (ShadowPathParams, "tissue_percentile", 100, r"must lie in \(0, 100\)"),
    (ShadowPathParams, "null_z", float("nan"), "must be finite"),
    (ShadowPathParams, "series_extend_deg", 90.0, r"must lie in \(0, 90\), got 90.0"),
    (SnakeParams, "n_points", 2, r"must lie in \[3, 100000\]"),
    (SnakeParams, "tau", 0.0, "must be > 0"),
    (SnakeParams, "max_iterations", "300", "must be an integer, got '300'"),
    (PosteriorParams, "neighbour_px", -10, "must be > 0"),
    (RejectionParams, "max_skip", -1, "must be >= 0, got -1"),
    (RejectionParams, "min_track_frames", 1.5, "must be an integer"),
    (RejectionParams, "min_overlap_share", 1.5, r"must lie in \[0, 1\]"),
    (RecoveryParams, "min_share", 1.5, r"must lie in \[0, 1\]"),
    (RecoveryParams, "max_offset", 0.0, "must be > 0"),
    (RecoveryParams, "enabled", 1, "must be True or False"),
    (RecoveryParams, "recheck", 1, "must be True or False"),
    (RecoveryParams, "min_stray", -0.1, "must be >= 0"),
    (RecoveryParams, "max_stray_ratio", 1.5, r"must lie in \[0, 1\]"),
    (RecoveryParams, "contact_level", 1.5, r"must lie in \[0, 1\]"),
    (SimulationParams, "min_depth_mm", -1.0, "must be >= 0, got -1.0"),
    (SegmentationParams, "snake", ShadowPathParams(), "must be a SnakeParams"),
    (FitParams, "degree", (2.7, 2), r"must be an integer, got 2.7"),
    (FitParams, "degree", (2, 2, 2), r"must have 2 values"),
    (FitParams, "n_control_points", "15 5", "must be a sequence"),
    (FitParams, "robust_iterations", -1, "must be >= 0"),
    (FitParams, "per_frame", 1, "must be True or False"),
    (ResamplingParams, "n_rays", 15.9, "must be an integer, got 15.9"),
    (ResamplingParams, "auto_span_quantile", 0.6, r"must lie in \[0, 0.5\]"),
    (ResamplingParams, "min_radius_mm", 0, "must be > 0"),
    (SurfaceParams, "step_mm", "0.5", "must be a number"),
    (LiveParams, "queue_frames", 6.5, "must be an integer"),
    (RegistrationParams, "max_iterations", 10.5, "must be an integer"),
    (RegistrationParams, "start_rolls_deg", 15.0, "must be a sequence"),
    (SimulationParams, "seed", -1, "must be >= 0"),
    (SimulationParams, "n_frames", 20.5, "must be an integer"),
    (SimulationParams, "frame_rate_hz", 0, "must be > 0"),
    (ImagingParams, "psf_axial_mm", 0, "must be > 0"),
    (ImagingParams, "tgc_compensation", 1.5, r"must lie in \[0, 1\]"),
    (HardParams, "depth_mm", (25.0, -5.0), "must be > 0"),
    (HardParams, "gap_copies", 2.5, "must be an integer"),
    (ReconstructionParams, "fit", ResamplingParams(), "must be a FitParams"),
]


@pytest.mark.parametrize(
    "cls, name, value, says", BAD, ids=[f"{c.__name__}.{n}={v!r}" for c, n, v, _ in BAD]
)
def test_bad_value_refused_naming_field_and_value(cls, name, value, says) -> None:
    with pytest.raises(BoneUSReconError, match=f"^{cls.__name__}.{name} {says}") as info:
        cls(**{name: value})
    assert isinstance(info.value, ValueError)  # the CLI's one-line error; Slicer's dialog


def test_a_wrong_type_is_also_a_type_error() -> None:
    with pytest.raises(TypeError):
        ResamplingParams(n_rays=15.9)
    assert issubclass(ParameterTypeError, BoneUSReconError)


@pytest.mark.parametrize(
    "cls, changes, expected",
    [
        (FitParams, {"degree": (np.int64(3), 2.0)}, {"degree": (3, 2)}),
        (FitParams, {"n_control_points": np.array([9, 4])}, {"n_control_points": (9, 4)}),
        (FitParams, {"per_frame": np.bool_(False)}, {"per_frame": False}),
        (
            ResamplingParams,
            {"n_rays": np.int32(21), "max_gap_mm": 2},
            {"n_rays": 21, "max_gap_mm": 2.0},
        ),
        (
            ShadowPathParams,
            {"n_passes": 2.0, "phase_wavelengths_mm": [1, 2]},
            {"n_passes": 2, "phase_wavelengths_mm": (1.0, 2.0)},
        ),
        (LiveParams, {"max_frames": np.uint16(50)}, {"max_frames": 50}),
        (
            SimulationParams,
            {"n_frames": 12.0, "spacing_mm": np.float32(0.25)},
            {"n_frames": 12, "spacing_mm": 0.25},
        ),
        (RegistrationParams, {"start_shifts_mm": [5, 10]}, {"start_shifts_mm": (5.0, 10.0)}),
        (SurfaceParams, {"gap_factor": None, "step_mm": 1}, {"gap_factor": None, "step_mm": 1.0}),
    ],
)
def test_good_values_coerced_to_declared_types(cls, changes, expected) -> None:
    p = cls(**changes)
    for name, want in expected.items():
        got = getattr(p, name)
        assert got == want and type(got) is type(want), (name, got)
        if isinstance(got, tuple):
            assert all(type(x) is type(want[0]) for x in got)


@pytest.mark.parametrize(
    "cls",
    [
        ShadowPathParams,
        SnakeParams,
        PosteriorParams,
        RejectionParams,
        RecoveryParams,
        SegmentationParams,
        FitParams,
        ResamplingParams,
        SurfaceParams,
        LiveParams,
        RegistrationParams,
        SimulationParams,
        ImagingParams,
        HardParams,
        ReconstructionParams,
    ],
)
def test_defaults_pass_unchanged(cls) -> None:
    p = cls()
    assert dataclasses.replace(p) == p


def test_old_control_points_keyword_still_works_with_a_warning() -> None:
    with pytest.warns(DeprecationWarning, match="n_control_points"):
        old = FitParams(control_points=(9, 4))
    assert old == FitParams(n_control_points=(9, 4))
    with pytest.warns(DeprecationWarning):
        assert old.control_points == (9, 4)
    # Control points given to params_with (not the default's) are fitted as asked or
    # refused: FitParams.fewer_if_short off.
    asked = FitParams(n_control_points=(9, 4), fewer_if_short=False)
    with pytest.warns(DeprecationWarning):
        assert params_with(control_points=(9, 4)).fit == asked
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert params_with(along=9, around=4).fit == asked
        assert params_with(n_control_points=(9, 5), around=4).fit == asked


@pytest.mark.parametrize("counts", [("a", 5), (15.5, 6), (None, 5)])
def test_params_with_refuses_bad_control_points_with_its_own_error(counts) -> None:
    # Refused by FitParams (a BoneUSReconError naming the field), not by a bare int().
    with pytest.raises(ParameterTypeError, match="n_control_points"):
        params_with(n_control_points=counts)
    # The default's count, however spelt, stays a ceiling; another is fitted as asked.
    assert params_with(n_control_points=(15.0, 6)).fit.fewer_if_short
    assert not params_with(along=9).fit.fewer_if_short
