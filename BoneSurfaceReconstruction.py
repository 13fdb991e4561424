"""Bone Surface Reconstruction: 3D Slicer scripted module over the BoneUSRecon library.

Layout after Slicer's scripted-module template: module metadata, parameter node,
Widget, Logic, Test. The Logic is a thin adapter: the scene <-> library conversion
lives in ``BoneSurfaceReconstructionLib.mrml`` and the computation in ``BoneUSRecon.Logic``;
helpers live in ``BoneSurfaceReconstructionLib`` (never beside this file: Slicer would
load each ``.py`` there as a module).
"""

import logging
import os
import pathlib
from typing import Annotated, Optional, Union

import qt
import slicer
import vtk
from slicer import (
    vtkMRMLLinearTransformNode,
    vtkMRMLMarkupsFiducialNode,
    vtkMRMLModelNode,
    vtkMRMLSequenceBrowserNode,
    vtkMRMLSequenceNode,
)
from slicer.i18n import tr as _
from slicer.i18n import translate
from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper
from slicer.ScriptedLoadableModule import (
    ScriptedLoadableModule,
    ScriptedLoadableModuleLogic,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
)
from slicer.util import VTKObservationMixin

# This file and BoneSurfaceReconstructionLib stay importable by Python 3.9 (Slicer 5.8
# and earlier), so that such a Slicer shows why the module cannot run instead of a
# SyntaxError; the library itself needs Python 3.10 (dependencies.MIN_PYTHON).
from BoneSurfaceReconstructionLib import dependencies
from BoneSurfaceReconstructionLib.parameters import (
    FLOAT_PARAMETERS,
    INT_PARAMETERS,
    segmenterNames,
)

_UNSUPPORTED = dependencies.unsupportedReason()

_SEGMENTERS = segmenterNames()


# Defaults and ranges come from one table (BoneSurfaceReconstructionLib.parameters).
_NUMBER_PARAMETERS = {**INT_PARAMETERS, **FLOAT_PARAMETERS}
_DEFAULT = {name: v[0] for name, v in _NUMBER_PARAMETERS.items()}
_RANGE = {name: (v[1], v[2]) for name, v in _NUMBER_PARAMETERS.items()}


#
# BoneSurfaceReconstruction
#


class BoneSurfaceReconstruction(ScriptedLoadableModule):
    """Module metadata (see ScriptedLoadableModule in Slicer's Base/Python)."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = _("Bone Surface Reconstruction")
        self.parent.categories = [translate("qSlicerAbstractCoreModule", "Ultrasound")]
        self.parent.dependencies = ["Sequences"]
        self.parent.contributors = ["BoneUSRecon developers"]
        self.parent.helpText = _(
            "Reconstructs the imaged bone surface from a tracked freehand ultrasound sweep "
            "(a sequence browser, or a volume sequence with its transform sequence): bone "
            "contours are segmented in each frame, resampled along rays, and approximated "
            "by a tensor-product B-spline surface, after Lopez-Perez et al., 'Bone Surface "
            "Reconstruction Using Localized Freehand Ultrasound Imaging'. The output model "
            "is coloured by its distance (mm) to the nearest segmented point. Optionally "
            "(Flank extension) the surface is continued down the bone's flanks past the "
            "data: those points are extrapolated, flagged by the point array "
            "'Extrapolated'."
        )
        self.parent.acknowledgementText = _(
            "Built on the BoneUSRecon library. Layout after Slicer's scripted-module "
            "template (Jean-Christophe Fillion-Robin, Kitware; Andras Lasso, PerkLab; "
            "Steve Pieper, Isomics)."
        )
        if _UNSUPPORTED:
            self.parent.helpText = _UNSUPPORTED + "\n\n" + self.parent.helpText
        else:
            # The PLUS recording shipped with the module, in the Sample Data module.
            slicer.app.connect("startupCompleted()", _registerSampleData)


def _registerSampleData() -> None:
    from BoneSurfaceReconstructionLib import sampledata

    sampledata.registerSampleData()


#
# BoneSurfaceReconstructionParameterNode
#


@parameterNodeWrapper
class BoneSurfaceReconstructionParameterNode:
    """The module's parameters, saved with the scene.

    inputNode - the sweep: a sequence browser (frames and their transforms as Slicer
        shows them), or a volume sequence.
    transformSequence - with a volume sequence outside any browser: its per-frame
        ImageToReference transforms (optional).
    calibrationFile - optional PLUS configuration XML whose Image->Probe transform maps
        pixels to probe mm (then the frames must sit under the probe's transform).
    segmenter - bone contour segmenter ("snake" is the paper's).
    controlPointsU/V, degreeU/V - the B-spline surface (paper: 15 x 5, quadratic; default 15 x 6).
    rays - rays per frame when resampling (paper: 15; default 24).
    flankExtension - mm the surface is continued down the bone's flanks past the data
        (extrapolated, flagged by the point array "Extrapolated"; 0: off, the default).
    bonePoints - optional point list on the bone to follow (world mm): where two bones
        are in view, the track follows the one through its points.
    outputSurface, outputPoints - where the results go (created if empty).
    targetModel - optional bone model (CT/MRI, mm) to register the surface to;
        outputTransform (surface -> model) and registeredModel receive the result.
    """

    # typing.Union, not X | Y: parameterNodeWrapper recognises typing.Union of nodes.
    inputNode: Union[vtkMRMLSequenceBrowserNode, vtkMRMLSequenceNode]  # noqa: UP007
    transformSequence: vtkMRMLSequenceNode
    calibrationFile: pathlib.Path
    segmenter: Annotated[str, Choice(list(_SEGMENTERS))] = _SEGMENTERS[0]
    controlPointsU: Annotated[int, WithinRange(*_RANGE["controlPointsU"])] = _DEFAULT[
        "controlPointsU"
    ]
    controlPointsV: Annotated[int, WithinRange(*_RANGE["controlPointsV"])] = _DEFAULT[
        "controlPointsV"
    ]
    degreeU: Annotated[int, WithinRange(*_RANGE["degreeU"])] = _DEFAULT["degreeU"]
    degreeV: Annotated[int, WithinRange(*_RANGE["degreeV"])] = _DEFAULT["degreeV"]
    rays: Annotated[int, WithinRange(*_RANGE["rays"])] = _DEFAULT["rays"]
    flankExtension: Annotated[float, WithinRange(*_RANGE["flankExtension"])] = _DEFAULT[
        "flankExtension"
    ]
    outputSurface: vtkMRMLModelNode
    outputPoints: Union[vtkMRMLModelNode, vtkMRMLMarkupsFiducialNode]  # noqa: UP007
    targetModel: vtkMRMLModelNode
    outputTransform: vtkMRMLLinearTransformNode
    registeredModel: vtkMRMLModelNode
    bonePoints: vtkMRMLMarkupsFiducialNode


#
# BoneSurfaceReconstructionWidget
#


class BoneSurfaceReconstructionWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """The module panel: binds the .ui to the parameter node; Apply calls the logic."""

    def __init__(self, parent=None) -> None:
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None

    def setup(self) -> None:
        ScriptedLoadableModuleWidget.setup(self)
        if _UNSUPPORTED:  # say why, instead of a panel that cannot work
            label = qt.QLabel(_UNSUPPORTED)
            label.wordWrap = True
            self.layout.addWidget(label)
            self.layout.addStretch(1)
            return
        uiWidget = slicer.util.loadUI(self.resourcePath("UI/BoneSurfaceReconstruction.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        for name, (_default, _lo, _hi, tip) in _NUMBER_PARAMETERS.items():
            getattr(self.ui, name + "SpinBox").toolTip = tip

        self.logic = BoneSurfaceReconstructionLogic()

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.loadSweepButton.connect("clicked(bool)", self.onLoadSweepButton)
        self.initializeParameterNode()
        from BoneSurfaceReconstructionLib.live import addLiveSection

        self.livePanel = addLiveSection(self)  # Live mode (OpenIGTLink): see that file

    def cleanup(self) -> None:
        if getattr(self, "livePanel", None) is not None:
            self.livePanel.stop()
        self.removeObservers()

    def enter(self) -> None:
        self.initializeParameterNode()

    def exit(self) -> None:
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            self.removeObserver(
                self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply
            )

    def onSceneStartClose(self, caller, event) -> None:
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event) -> None:
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self) -> None:
        self.setParameterNode(self.logic.getParameterNode())
        # Save the user a click: pick the first sequence browser in the scene.
        if not self._parameterNode.inputNode:
            browser = slicer.mrmlScene.GetFirstNodeByClass("vtkMRMLSequenceBrowserNode")
            if browser:
                self._parameterNode.inputNode = browser

    def setParameterNode(
        self,
        inputParameterNode: Optional[BoneSurfaceReconstructionParameterNode],  # noqa: UP045 (Python 3.9)
    ) -> None:
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self.removeObserver(
                self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply
            )
        self._parameterNode = inputParameterNode
        if self._parameterNode:
            self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
            self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
            self._checkCanApply()

    def _checkCanApply(self, caller=None, event=None) -> None:
        if self._parameterNode and self._parameterNode.inputNode:
            self.ui.applyButton.toolTip = _("Reconstruct the bone surface")
            self.ui.applyButton.enabled = True
        else:
            self.ui.applyButton.toolTip = _(
                "Select an input sweep (sequence browser or volume sequence)"
            )
            self.ui.applyButton.enabled = False

    def onApplyButton(self) -> None:
        """Install missing packages (once, if the user agrees), then run the logic."""
        with slicer.util.tryWithErrorDisplay(
            _("Failed to reconstruct the bone surface."), waitCursor=True
        ):
            dependencies.installRequirements(confirm=slicer.util.confirmOkCancelDisplay)
            dialog = slicer.util.createProgressDialog(
                labelText=_("Reconstructing the bone surface..."), maximum=100
            )
            try:
                result = self.logic.processParameterNode(
                    self._parameterNode, progress=self._progressCallback(dialog)
                )
            finally:
                dialog.close()
            # Cancel is not a failure: no error dialog, the outputs are left as they were.
            self.ui.resultLabel.text = (
                _("Cancelled.") if result is None else self.logic.summaryText(result)
            )

    def onLoadSweepButton(self) -> None:
        """Read a PLUS file with BoneUSRecon's reader (pose chain, calibration, status
        flags) into a new sequence browser, and make it the input."""
        path = qt.QFileDialog.getOpenFileName(
            self.parent, _("Load a PLUS sequence file"), "", _("PLUS sequence (*.mha *.mhd)")
        )
        if not path:
            return
        with slicer.util.tryWithErrorDisplay(_("Failed to load the sweep."), waitCursor=True):
            dependencies.installRequirements(confirm=slicer.util.confirmOkCancelDisplay)
            calibration = self._parameterNode.calibrationFile
            browser = self.logic.loadSweepFile(path, calibration)
            self._parameterNode.inputNode = browser
            # The calibration is now inside the poses: applying it again would be wrong.
            self._parameterNode.calibrationFile = pathlib.Path()
            self.ui.resultLabel.text = _("Loaded {name}: {n} frames.").format(
                name=browser.GetName(), n=browser.GetNumberOfItems()
            )

    def _progressCallback(self, dialog):
        """A plain ``progress(stage, done, total)`` callback driving a Qt progress dialog;
        its Cancel button only sets the logic's flag, which the logic polls."""

        def progress(stage, done, total):
            if dialog.wasCanceled:
                self.logic.requestCancel()
            dialog.labelText = f"{stage}: {done}/{total}"
            dialog.value = int(100 * done / total) if total else 0
            slicer.app.processEvents()

        return progress


#
# BoneSurfaceReconstructionLogic
#


class BoneSurfaceReconstructionLogic(ScriptedLoadableModuleLogic):
    """Scene nodes -> BoneUSRecon -> scene nodes. Usable without the Widget; raises, never
    shows dialogs (BoneUSReconError is a ValueError with a one-line message).
    """

    def __init__(self) -> None:
        ScriptedLoadableModuleLogic.__init__(self)
        self._cancelRequested = False

    def requestCancel(self) -> None:
        """Ask the running :meth:`process` to stop at its next progress step.

        A flag, polled through the progress callback (``BoneUSRecon.Logic.progress.
        cancellable``): the work stops within one frame, :meth:`process` returns None
        and no output node is created or changed.
        """
        self._cancelRequested = True

    def getParameterNode(self):
        return BoneSurfaceReconstructionParameterNode(super().getParameterNode())

    def process(
        self,
        inputNode,
        transformSequence=None,
        calibration=None,
        segmenter=None,
        controlPointsU=_DEFAULT["controlPointsU"],
        controlPointsV=_DEFAULT["controlPointsV"],
        degreeU=_DEFAULT["degreeU"],
        degreeV=_DEFAULT["degreeV"],
        rays=_DEFAULT["rays"],
        flankExtension=_DEFAULT["flankExtension"],
        outputSurface=None,
        outputPoints=None,
        progress=None,
        targetModel=None,
        outputTransform=None,
        registeredModel=None,
        bonePoints=None,
    ):
        """Reconstruct the bone surface of a sweep in the scene (explicit arguments).

        :param inputNode: sequence browser, volume sequence, or a browser's image proxy.
        :param transformSequence: per-frame transforms, for a volume sequence outside any browser.
        :param calibration: PLUS configuration XML path, 4x4 ImageToProbe array, or
            linear transform node; None to use the frames' own geometry.
        :param segmenter: a name of BoneUSRecon.Logic.segmentation.SEGMENTERS (None: default).
        :param controlPointsU, controlPointsV: B-spline control points along and across (e, f).
        :param degreeU, degreeV: B-spline degrees along and across (p, q).
        :param rays: rays per frame.
        :param flankExtension: mm the surface is continued down the bone's flanks past
            the data (0: off); those points are flagged by the point array "Extrapolated".
            These seven are the parameter node's values, made library parameters by
            BoneSurfaceReconstructionLib.parameters.parameters_from_widget_values.
        :param outputSurface: model node to fill (new if None).
        :param outputPoints: model or markups fiducial node to fill (new if None).
        :param progress: callable(stage, done, total).
        :param targetModel: bone model node to register the surface to (None: no registration).
        :param outputTransform: linear transform node for surface -> model (new if None).
        :param registeredModel: model node for the registered surface (new if None).
        :param bonePoints: markups point list whose points lie on the bone to follow
            (None: the default choice, the bone nearest the middle of the image).
        :return: BoneSurfaceReconstructionLib.mrml.MRMLReconstruction (its ``registration`` set
            when a target model was given), or None when cancelled (:meth:`requestCancel`).
        """
        import time

        from BoneSurfaceReconstructionLib import mrml
        from BoneSurfaceReconstructionLib.parameters import (
            calibrationMatrix,
            parameters_from_widget_values,
        )
        from BoneUSRecon.Logic.progress import Cancelled, cancellable

        if not inputNode:
            raise ValueError(_("Input sweep is invalid."))
        if isinstance(calibration, (str, os.PathLike)):
            calibration = calibrationMatrix(calibration)
        params = parameters_from_widget_values(
            {
                "segmenter": segmenter,
                "controlPointsU": controlPointsU,
                "controlPointsV": controlPointsV,
                "degreeU": degreeU,
                "degreeV": degreeV,
                "rays": rays,
                "flankExtension": flankExtension,
            }
        )
        if bonePoints is not None:
            from BoneUSRecon.Logic.pipeline import params_with

            params = params_with(params, bone_points=mrml.bone_points_from_node(bonePoints))
        startTime = time.time()
        logging.info("Bone surface reconstruction started")
        self._cancelRequested = False
        try:
            result = mrml.reconstruct_from_scene(
                inputNode,
                transform_sequence=transformSequence,
                calibration=calibration,
                params=params,
                surface_node=outputSurface,
                points_node=outputPoints,
                progress=cancellable(lambda: self._cancelRequested, progress),
            )
        except Cancelled as exc:
            logging.info(f"Bone surface reconstruction {exc}")
            return None
        finally:
            self._cancelRequested = False
        logging.info(
            f"Bone surface reconstruction completed in {time.time() - startTime:.2f} seconds"
        )
        if targetModel:
            import dataclasses

            from BoneSurfaceReconstructionLib.registration import registerModelToModel

            # The segmented points (in world coordinates, as the surface) are registered:
            # they lie on the imaged bone, the fitted surface only near it.
            registration = registerModelToModel(
                result.surface_node,
                targetModel,
                transformNode=outputTransform,
                registeredNode=registeredModel,
                reconstruction=result.reconstruction,
            )
            result = dataclasses.replace(result, registration=registration)
        return result

    def loadSweepFile(self, path, calibration=None, progress=None):
        """Read a PLUS .mha/.mhd with BoneUSRecon's reader into a new sequence browser.

        :param path: the sequence file.
        :param calibration: PLUS configuration XML (Image->Probe), or None / empty path.
        :return: the vtkMRMLSequenceBrowserNode (frames under their ImageToReference).
        """
        from BoneSurfaceReconstructionLib import mrml
        from BoneSurfaceReconstructionLib.parameters import calibrationPath

        nodes = mrml.load_sweep_file(
            path, slicer.mrmlScene, calibration=calibrationPath(calibration), progress=progress
        )
        return nodes.browser

    def processParameterNode(self, parameterNode, progress=None):
        """Same as :meth:`process`, reading every argument from the parameter node and
        storing the created output nodes back into it."""
        from BoneSurfaceReconstructionLib.parameters import widgetValues

        p = parameterNode
        result = self.process(
            p.inputNode,
            transformSequence=p.transformSequence,
            calibration=p.calibrationFile,
            **widgetValues(p),
            outputSurface=p.outputSurface,
            outputPoints=p.outputPoints,
            progress=progress,
            targetModel=p.targetModel,
            outputTransform=p.outputTransform,
            registeredModel=p.registeredModel,
            bonePoints=p.bonePoints,
        )
        if result is None:  # cancelled
            return None
        p.outputSurface = result.surface_node
        p.outputPoints = result.points_node
        if result.registration is not None:
            p.outputTransform = result.registration.transformNode
            p.registeredModel = result.registration.registeredNode
        return result

    @staticmethod
    def summaryText(result) -> str:
        """A line for the panel: frames used, points, fit residual; then how much of the
        surface is extrapolated (flank extension), the warnings (a bone point the track
        does not reach) and the registration, if any."""
        sweep = result.sweep
        points = result.points_node
        nPoints = (
            points.GetNumberOfControlPoints()
            if points.IsA("vtkMRMLMarkupsNode")
            else points.GetPolyData().GetNumberOfPoints()
        )
        rms = getattr(result.reconstruction.fit, "rms_mm", float("nan"))
        text = _("{frames} frames, {points} segmented points, fit RMS {rms:.2f} mm").format(
            frames=sweep.n_valid, points=nPoints, rms=rms
        )
        flags = result.surface_node.GetPolyData().GetPointData().GetArray("Extrapolated")
        if flags is not None:
            from vtkmodules.util.numpy_support import vtk_to_numpy

            # Said on the panel: part of the model was not imaged.
            text += "\n" + _(
                "Flanks extended {mm:g} mm past the data: {n} of {total} surface points "
                "extrapolated (point array 'Extrapolated')."
            ).format(
                mm=result.reconstruction.params.surface.flank_extension_mm,
                n=int(vtk_to_numpy(flags).astype(bool).sum()),
                total=flags.GetNumberOfTuples(),
            )
        for warning in result.reconstruction.summary.get("warnings", ()):
            text += "\n" + warning  # e.g. a bone point the track does not reach
        if result.registration is not None:
            from BoneSurfaceReconstructionLib.registration import summaryText

            text += "\n" + summaryText(result.registration)
        return text


#
# BoneSurfaceReconstructionTest
#


class BoneSurfaceReconstructionTest(ScriptedLoadableModuleTest):
    """Self-test: a simulated clavicle sweep through the scene, checked in millimetres.

    Run it from the module panel (Reload & Test, developer mode) or with
    ``slicer.util.selectModule("BoneSurfaceReconstruction"); slicer.modules.BoneSurfaceReconstructionWidget.onReloadAndTest()``.
    """

    def setUp(self):
        slicer.mrmlScene.Clear()

    def runTest(self):
        if _UNSUPPORTED:
            self.delayDisplay(_UNSUPPORTED)
            return
        self.setUp()
        self.test_SimulatedSweepAccuracy()
        self.setUp()
        self.test_ParameterNodeEntryPoint()
        self.setUp()
        self.test_BadInputRaises()

    def test_SimulatedSweepAccuracy(self):
        """Reconstruct a simulated sweep through the scene; check the surface against the truth."""
        from BoneSurfaceReconstructionLib import selftest

        dependencies.installRequirements(
            confirm=None if slicer.app.testingEnabled() else slicer.util.confirmOkCancelDisplay
        )
        self.delayDisplay("Simulating a clavicle sweep and reconstructing it")
        result = selftest.runSelfTest(slicer.mrmlScene)
        logging.info(f"Self-test: {result}")
        self.assertEqual(result.failures(), [])
        self.assertGreater(result.nodes.surface_node.GetPolyData().GetNumberOfCells(), 0)
        self.assertEqual(
            result.nodes.surface_node.GetDisplayNode().GetActiveScalarName(), "Distance"
        )
        self.delayDisplay(
            f"Surface to truth {result.surface_to_truth_mean_mm:.2f} mm (mean), "
            f"gold to surface {result.gold_to_surface_mean_mm:.2f} mm: passed"
        )

    def test_ParameterNodeEntryPoint(self):
        """The parameter-node entry point gives the same surface as the explicit one."""
        from BoneSurfaceReconstructionLib import mrml, selftest

        sim = selftest.simulatedSweep(n_frames=30)
        nodes = mrml.sweep_to_scene(sim.sweep, slicer.mrmlScene, name="Sweep")
        logic = BoneSurfaceReconstructionLogic()
        p = logic.getParameterNode()
        p.inputNode = nodes.browser
        p.controlPointsU = 10
        viaNode = logic.processParameterNode(p)
        self.assertIs(p.outputSurface, viaNode.surface_node)
        explicit = logic.process(nodes.browser, controlPointsU=10)
        a = slicer.util.arrayFromModelPoints(viaNode.surface_node)
        b = slicer.util.arrayFromModelPoints(explicit.surface_node)
        self.assertEqual(a.shape, b.shape)
        self.assertLess(float(abs(a - b).max()), 1e-9)

    def test_BadInputRaises(self):
        """The logic raises a one-line ValueError (no dialog) on unusable input."""
        volume = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "NotASweep")
        logic = BoneSurfaceReconstructionLogic()
        with self.assertRaises(ValueError):
            logic.process(None)
        with self.assertRaises(ValueError):
            logic.process(volume)
