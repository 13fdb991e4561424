"""Live mode: the surface grows while OpenIGTLinkIF updates the incoming image.

Slicer's OpenIGTLinkIF module receives a PLUS server's IMAGE (and TRANSFORM) messages
into a scalar volume node, replacing its image data and ``IJKToRAS`` with every frame
(and the matrices of transform nodes it may sit under). :class:`LiveSurface` observes
that volume node, turns each new frame into ``(image, ImageToReference)`` exactly as
the scene's adapter does (``ParentTransformToWorld @ IJKToRAS``, or
``ParentTransformToWorld @ calibration`` with a PLUS ``ImageToProbe``), feeds
:class:`BoneUSRecon.Logic.live.LiveReconstructor`, and every ``update_every_s``
seconds puts the refitted surface in a model node coloured by ``Distance``.

An image and its pose are two updates (image data, matrix or transform), in an order
that depends on the server; so a frame is read once the current event has been
handled (``schedule``: a zero-delay Qt timer in Slicer), when both are in place.
Frames replaced faster than Slicer's event loop runs are seen once (the newest).

:func:`addLiveSection` adds the Live panel (volume, model, Start/Stop) to the module's
widget; it is the only part that needs Qt.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

# BoneUSRecon is imported when live mode starts, never when the widget is built: inside
# Slicer it may still have to be installed (see .dependencies).
if TYPE_CHECKING:
    from BoneUSRecon.Logic.live import LiveParams
    from BoneUSRecon.Logic.pipeline import Reconstruction, ReconstructionParams

__all__ = ["LiveSurface", "addLiveSection", "liveParameters"]


def _qt_schedule(fn: Callable[[], None]) -> None:
    """Run ``fn`` once Slicer's event loop is idle again (immediately without Qt)."""
    try:
        import qt
    except ImportError:
        fn()
        return
    qt.QTimer.singleShot(0, fn)


class LiveSurface:
    """Observe an incoming image volume node and keep a model node's surface up to date.

    Parameters
    ----------
    volume : vtkMRMLScalarVolumeNode
        The node OpenIGTLinkIF updates (e.g. ``Image_Reference``).
    model : vtkMRMLModelNode, optional
        Where the surface goes (a new ``BoneSurfaceLive`` model if None).
    calibration : ndarray (4, 4), optional
        PLUS ``ImageToProbe``; then the volume must sit under the probe's tracking
        transform and its own geometry is ignored, as in PLUS.
    params : ReconstructionParams, optional
    live : LiveParams, optional
        ``update_every_s`` and ``max_frames``.
    schedule : callable, optional
        ``schedule(fn)`` runs ``fn`` after the current event (default: a zero-delay
        Qt timer; tests run it at once).
    clock : callable, optional
        Seconds (default :func:`time.monotonic`).
    """

    def __init__(
        self,
        volume: Any,
        model: Any = None,
        *,
        calibration: np.ndarray | None = None,
        params: ReconstructionParams | None = None,
        live: LiveParams | None = None,
        schedule: Callable[[Callable[[], None]], None] = _qt_schedule,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from BoneUSRecon.Logic.errors import BoneUSReconError
        from BoneUSRecon.Logic.live import LiveParams, LiveReconstructor
        from BoneUSRecon.Logic.pipeline import ReconstructionParams

        if volume is None or not volume.IsA("vtkMRMLScalarVolumeNode"):
            raise BoneUSReconError("live mode needs the incoming image's scalar volume node")
        self._error = BoneUSReconError
        self.volume = volume
        self.scene = volume.GetScene()
        self.model = (
            model
            if model is not None
            else self.scene.AddNewNodeByClass("vtkMRMLModelNode", "BoneSurfaceLive")
        )
        self.calibration = None if calibration is None else np.asarray(calibration, float)
        self.live = live or LiveParams()
        self.reconstructor = LiveReconstructor(params or ReconstructionParams(), self.live)
        self._schedule = schedule
        self._clock = clock
        self._observers: list[tuple[Any, int]] = []
        self._scheduled = False
        self._last_mtime = -1
        self._due = 0.0
        self._new = 0
        #: Frames read, and frames that could not be used (``{reason: count}``).
        self.frames = 0
        self.skipped: dict[str, int] = {}
        self.result: Reconstruction | None = None
        self.waiting = ""

    @property
    def running(self) -> bool:
        """True between :meth:`start` and :meth:`stop`."""
        return bool(self._observers)

    def start(self) -> None:
        """Start observing the volume node (and the transform it sits under)."""
        if self.running:
            return
        self._due = self._clock() + self.live.update_every_s
        v = self.volume
        self._observers.append((v, v.AddObserver(v.ImageDataModifiedEvent, self._onModified)))
        self._observers.append((v, v.AddObserver(v.TransformModifiedEvent, self._onModified)))

    def stop(self) -> Reconstruction | None:
        """Stop observing; the final surface (all frames, as offline) goes in the model."""
        for node, tag in self._observers:
            node.RemoveObserver(tag)
        self._observers.clear()
        if self.reconstructor.n_frames:
            self._refit(final=True)
        return self.result

    def _onModified(self, caller: Any = None, event: Any = None) -> None:
        if not self._scheduled:
            self._scheduled = True
            self._schedule(self.process)

    def process(self) -> None:
        """Read the volume's current frame if it is new; refit when due."""
        self._scheduled = False
        image_data = self.volume.GetImageData()
        if image_data is None or image_data.GetMTime() == self._last_mtime:
            return  # a pose update alone, or the same frame again
        self._last_mtime = image_data.GetMTime()
        try:
            image, pose = self._frame()
        except self._error as exc:
            self.skipped[exc.message] = self.skipped.get(exc.message, 0) + 1
            return
        self.frames += 1
        if self.reconstructor.add_frame(image, pose, self._clock()) is not None:
            self._new += 1
        if self._clock() >= self._due and self._new:
            self._refit(final=False)
            self._due = self._clock() + self.live.update_every_s

    def _frame(self) -> tuple[np.ndarray, np.ndarray]:
        from BoneSurfaceReconstructionLib import mrml_sweep as mrml

        v = self.volume
        image = mrml._image_array(v.GetImageData(), mrml._node_label(v))
        if image.dtype != np.uint8:
            raise self._error(f"pixel type {image.dtype} (live mode needs 8-bit B-mode frames)")
        local = mrml._ijk_to_ras(v) if self.calibration is None else self.calibration
        return image, mrml._to_world(v) @ local

    def _refit(self, final: bool) -> None:
        from BoneSurfaceReconstructionLib import mrml

        try:
            self.result = self.reconstructor.refit(final=final, with_points=final)
        except self._error as exc:
            self.waiting = exc.message
            return
        self.waiting = ""
        self._new = 0
        mrml.show_surface(self.result.surface, self.scene, node=self.model)

    def statusText(self) -> str:
        """One line: frames, surface coverage or what it waits for; then the surface's
        warnings, one line each (e.g. a bone point off the scan, after :meth:`stop`)."""
        skipped = sum(self.skipped.values())
        text = f"{self.frames} frames, {skipped} skipped"
        if self.waiting:
            return f"{text}; waiting: {self.waiting}"
        if self.result is not None:
            s = self.result.summary
            text += (
                f"; surface from {s['segmented_frames']} frames, "
                f"{100 * s['grid_coverage']:.0f}% of the grid covered"
            )
            for warning in s.get("warnings", ()):
                text += "\n" + warning  # as the module's summary shows them
        return text


def liveParameters(parameterNode: Any) -> ReconstructionParams:
    """The live session's reconstruction parameters: the module's, as Apply takes them
    (:func:`~BoneSurfaceReconstructionLib.parameters.parameters_from_widget_values`),
    with the points of the panel's *Bone point* list as placed when the session starts
    (``RejectionParams.bone_points``; a point placed later is not seen).

    Parameters
    ----------
    parameterNode
        The module's parameter node (its reconstruction values and ``bonePoints``).

    Returns
    -------
    ReconstructionParams
    """
    from BoneSurfaceReconstructionLib.parameters import (
        parameters_from_widget_values,
        widgetValues,
    )

    params = parameters_from_widget_values(widgetValues(parameterNode))
    node = getattr(parameterNode, "bonePoints", None)
    if node is None:
        return params
    from BoneSurfaceReconstructionLib.mrml import bone_points_from_node
    from BoneUSRecon.Logic.pipeline import params_with

    return params_with(params, bone_points=bone_points_from_node(node))


def addLiveSection(widget: Any) -> Any:
    """Add the Live panel to the module widget; returns an object with ``stop()``.

    The panel: the incoming image volume (the node OpenIGTLinkIF updates), the output
    model, the refit interval, a Start/Stop button and a status line. Calibration and
    reconstruction parameters are the module's (its parameter node).
    """
    import ctk
    import qt
    import slicer

    box = ctk.ctkCollapsibleButton()
    box.text = "Live (OpenIGTLink)"
    box.collapsed = True
    form = qt.QFormLayout(box)
    volumeSelector = slicer.qMRMLNodeComboBox()
    volumeSelector.nodeTypes = ["vtkMRMLScalarVolumeNode"]
    volumeSelector.noneEnabled = True
    volumeSelector.addEnabled = False
    volumeSelector.setMRMLScene(slicer.mrmlScene)
    volumeSelector.toolTip = "The image volume OpenIGTLinkIF updates (e.g. Image_Reference)"
    form.addRow("Incoming image:", volumeSelector)
    modelSelector = slicer.qMRMLNodeComboBox()
    modelSelector.nodeTypes = ["vtkMRMLModelNode"]
    modelSelector.noneEnabled = True
    modelSelector.addEnabled = True
    modelSelector.renameEnabled = True
    modelSelector.setMRMLScene(slicer.mrmlScene)
    modelSelector.toolTip = "Model that shows the growing surface (new if none)"
    form.addRow("Live surface:", modelSelector)
    every = qt.QDoubleSpinBox()
    every.setRange(0.2, 60.0)
    every.value = 1.0
    every.suffix = " s"
    form.addRow("Update every:", every)
    button = qt.QPushButton("Start")
    button.checkable = True
    form.addRow(button)
    status = qt.QLabel("")
    status.wordWrap = True
    form.addRow(status)
    widget.layout.addWidget(box)

    class _Panel:
        live: LiveSurface | None = None
        timer = qt.QTimer()

        def toggle(self, checked: bool) -> None:
            if checked:
                self.start()
            else:
                self.stop()

        def start(self) -> None:
            from BoneSurfaceReconstructionLib import dependencies
            from BoneSurfaceReconstructionLib.parameters import calibrationMatrix

            node = widget._parameterNode
            try:
                dependencies.requireBoneUSRecon()
                from BoneUSRecon.Logic.live import LiveParams

                params = liveParameters(node) if node else None
                cal = calibrationMatrix(node.calibrationFile) if node else None
                self.live = LiveSurface(
                    volumeSelector.currentNode(),
                    modelSelector.currentNode(),
                    calibration=cal,
                    params=params,
                    live=LiveParams(update_every_s=every.value),
                )
            except (
                ValueError,
                AttributeError,
                ImportError,
            ) as exc:  # BoneUSReconError is a ValueError
                button.checked = False
                status.text = f"Cannot start: {exc}"
                return
            modelSelector.setCurrentNode(self.live.model)
            self.live.start()
            button.text = "Stop"
            self.timer.start(500)

        def stop(self) -> None:
            self.timer.stop()
            if self.live is not None:
                self.live.stop()
                status.text = "Stopped: " + self.live.statusText()
            self.live = None
            button.text = "Start"
            button.checked = False

        def refresh(self) -> None:
            if self.live is not None:
                status.text = self.live.statusText()

    panel = _Panel()
    button.connect("toggled(bool)", panel.toggle)
    panel.timer.connect("timeout()", panel.refresh)
    return panel
