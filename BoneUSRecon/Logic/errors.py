"""The one error type users see.

Every problem with the user's input (a file, a parameter) raises
:class:`BoneUSReconError`. The CLI prints it as a single line
``bone-us-recon: error: <path>: <message>`` and exits with status 2; the Slicer
module shows it in its error dialog. It derives from :class:`ValueError`, as the
Slicer template asks of logic errors.

Messages speak of files and values, never of command-line options: the Slicer module
shows the same text. When a problem is about one argument of a Logic function
(``calibration=``, ``transform=``), the error names it in :attr:`~BoneUSReconError.parameter`
and the CLI adds its own option name (``BoneUSRecon.cli.common.with_option_names``).
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
    parameter : str, optional
        The Logic function's argument the problem is about (e.g. ``"calibration"``),
        for front ends that name it their own way.

    Examples
    --------
    >>> err = BoneUSReconError("DimSize disagrees\\nwith the data", "s.mha")
    >>> str(err), err.path, err.parameter
    ('s.mha: DimSize disagrees with the data', 's.mha', None)
    >>> isinstance(err, ValueError)
    True
    """

    def __init__(
        self,
        message: str,
        path: str | os.PathLike[str] | None = None,
        *,
        parameter: str | None = None,
    ) -> None:
        # One line, always: multi-line text would break the CLI's one-line contract.
        self.message = " ".join(str(message).split())
        self.path = None if path is None else os.fspath(path)
        self.parameter = parameter
        super().__init__(self.__str__())

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message
