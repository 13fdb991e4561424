"""The kept points as ``vtkPolyData`` (the VTK edge of the segmentation stage)."""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from BoneUSRecon.Logic.segmentation.result import SegmentationResult
from BoneUSRecon.Logic.sweep import Sweep
from BoneUSRecon.Logic.vtkio import points_to_polydata

__all__ = ["points_polydata"]


def points_polydata(result: SegmentationResult, sweep: Sweep) -> vtkPolyData:
    """Kept points in reference mm with point arrays ``Frame``, ``Intensity``, ``Confidence``."""
    pts, frame, inten, conf = result.points_mm(sweep)
    return points_to_polydata(
        pts,
        {
            "Frame": frame.astype(np.int32),
            "Intensity": inten.astype(np.float32),
            "Confidence": conf.astype(np.float32),
        },
    )
