"""The one error type users see.

Every problem with the user's input (a file, a parameter) raises
:class:`BoneUSReconError`. The CLI prints it as a single line
``bone-us-recon: error: <path>: <message>`` and exits with status 2; the Slicer
module shows it in its error dialog. It derives from :class:`ValueError`, as the
Slicer template asks of logic errors.
"""

from __future__ import annotations

import os

__all__ = ["BoneUSReconError"]


class BoneUSReconError(ValueError):
    """Invalid input: names the file (if any) and the problem, on one line.

    Parameters
    ----------
    message : str
        What is wrong, e.g. ``"DimSize says 21 frames but the data holds 20"``.
    path : str or os.PathLike, optional
        The file the problem is in.
    """

    def __init__(self, message: str, path: str | os.PathLike[str] | None = None) -> None:
        # One line, always: multi-line text would break the CLI's one-line contract.
        self.message = " ".join(str(message).split())
        self.path = None if path is None else os.fspath(path)
        super().__init__(self.__str__())

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message
