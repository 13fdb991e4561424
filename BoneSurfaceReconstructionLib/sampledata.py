"""The PLUS recording shipped with the module, registered in Slicer's Sample Data module.

``Resources/SampleData/BoneUltrasound_L14.igs.mha`` (BSD 3-Clause, PLUS toolkit; see its
``LICENSE`` and ``README.md``) appears in *Sample Data* under *Ultrasound*; Slicer checks
the file against :data:`SHA256` before loading it as a sequence. The URI is the file
beside the module (``file://``), so it works offline and in an installed extension.
Importing this file does not import ``slicer``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

__all__ = ["SAMPLE_NAME", "FILE_NAME", "SHA256", "samplePath", "registerSampleData"]

SAMPLE_NAME = "BoneUltrasound_L14"
FILE_NAME = "BoneUltrasound_L14.igs.mha"
#: SHA256 of the shipped file (also in Resources/SampleData/README.md).
SHA256 = "8a6eccb91ea19bde3377ba1d63ebaeed39234f551f768569bdc48f70e3675127"
CATEGORY = "Ultrasound"


def samplePath() -> Path:
    """The recording in the module's ``Resources/SampleData`` folder."""
    return Path(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))) / (
        f"Resources/SampleData/{FILE_NAME}"
    )


def registerSampleData(sampleDataLogic: Any = None) -> None:
    """Add the recording to the Sample Data module (call once Slicer has started).

    Parameters
    ----------
    sampleDataLogic : class, optional
        ``SampleData.SampleDataLogic`` (default: imported here, inside Slicer).
    """
    if sampleDataLogic is None:
        import SampleData  # Slicer's Sample Data module

        sampleDataLogic = SampleData.SampleDataLogic
    icon = Path(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))) / (
        "Resources/Icons/BoneSurfaceReconstruction.png"
    )
    sampleDataLogic.registerCustomSampleDataSource(
        category=CATEGORY,
        sampleName=SAMPLE_NAME,
        thumbnailFileName=str(icon),
        uris=samplePath().as_uri(),
        fileNames=FILE_NAME,
        nodeNames=SAMPLE_NAME,
        checksums=f"SHA256:{SHA256}",
        loadFileType="SequenceFile",
    )
