"""The dock widget: pick an Image or Labels layer, set the main parameters, run
vesselflow in a worker thread with a progress bar and a Cancel button."""

from __future__ import annotations

import threading
from typing import Any

import napari
from magicgui.widgets import ComboBox, Container, FloatSpinBox, ProgressBar, PushButton, SpinBox
from napari.qt.threading import thread_worker
from napari.utils.notifications import show_error, show_info
from superqt.utils import ensure_main_thread

from vesselflow.napari._layers import LayerData
from vesselflow.napari._run import Cancelled, skeletonize_layer


class SkeletonizeWidget(Container[Any]):  # type: ignore[misc, unused-ignore]
    """Run vesselflow on an Image or Labels layer; the graph is added as layers.

    The spacing is the layer's ``scale``; a Labels layer is binarised at the label
    chosen (0: any non-zero), an Image layer at the threshold chosen (below its
    minimum: taken as a mask as it is).
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        super().__init__()
        self._viewer = napari_viewer
        self._layer_box = ComboBox(label="layer", choices=self._layer_choices)
        self._threshold_box = FloatSpinBox(
            label="threshold", value=-1.0, min=-1e12, max=1e12, step=0.1
        )
        self._label_box = SpinBox(label="label", value=0, min=0, max=2**31 - 1)
        self._gamma_box = FloatSpinBox(label="gamma", value=0.05, min=1e-6, max=1e3, step=0.01)
        self._refine_box = FloatSpinBox(label="refine_area", value=50.0, min=0.0, max=1e9)
        self._max_iterations_box = SpinBox(label="max_iterations", value=100, min=0, max=100000)
        self._prune_box = FloatSpinBox(label="prune (length/radius)", value=0.0, min=0.0, max=100.0)
        self._run_button = PushButton(text="Run")
        self._cancel_button = PushButton(text="Cancel", enabled=False)
        self._progress_bar = ProgressBar(label="progress", value=0, max=100, visible=False)
        self.extend(
            [
                self._layer_box,
                self._threshold_box,
                self._label_box,
                self._gamma_box,
                self._refine_box,
                self._max_iterations_box,
                self._prune_box,
                self._run_button,
                self._cancel_button,
                self._progress_bar,
            ]
        )
        self._stop = threading.Event()
        self._run_button.changed.connect(self.start)
        self._cancel_button.changed.connect(self._stop.set)

    def _layer_choices(self, _: Any = None) -> list[Any]:
        kinds = (napari.layers.Image, napari.layers.Labels)
        return [layer for layer in self._viewer.layers if isinstance(layer, kinds)]

    def start(self) -> Any:
        """Start a run on the chosen layer in a worker thread; returns the worker."""
        layer: Any = self._layer_box.value
        if layer is None:
            show_error("vesselflow: no Image or Labels layer to skeletonize")
            return None
        is_labels = isinstance(layer, napari.layers.Labels)
        threshold = (
            None if is_labels or self._threshold_box.value < 0 else self._threshold_box.value
        )
        label = self._label_box.value if is_labels and self._label_box.value > 0 else None
        prune = self._prune_box.value or None
        params = {
            "gamma": self._gamma_box.value,
            "refine_area": self._refine_box.value,
            "max_iterations": self._max_iterations_box.value,
        }
        self._stop.clear()

        @thread_worker  # type: ignore[untyped-decorator, unused-ignore]
        def work() -> list[LayerData]:
            return skeletonize_layer(
                layer.data,
                layer.scale,
                layer.translate,
                name=layer.name,
                params=params,
                threshold=threshold,
                label=label,
                prune_min_length_over_radius=prune,
                progress=self._show_progress,
                cancelled=self._stop.is_set,
            )

        worker = work()
        worker.returned.connect(self._add_layers)
        worker.errored.connect(self._failed)
        worker.finished.connect(self._done)
        self._run_button.enabled, self._cancel_button.enabled = False, True
        self._progress_bar.visible, self._progress_bar.value = True, 0
        worker.start()
        return worker

    @ensure_main_thread  # type: ignore[untyped-decorator, unused-ignore]
    def _show_progress(self, stage: str, iteration: int, max_iterations: int) -> None:
        self._progress_bar.max = max(max_iterations, 1)
        self._progress_bar.value = min(iteration, self._progress_bar.max)
        self._progress_bar.label = stage

    def _add_layers(self, layers: list[LayerData]) -> None:
        for data, kwargs, kind in layers:
            getattr(self._viewer, f"add_{kind}")(data, **kwargs)

    def _failed(self, error: BaseException) -> None:
        if isinstance(error, Cancelled):
            show_info("vesselflow: run cancelled")
        else:
            show_error(f"vesselflow: {error}")

    def _done(self) -> None:
        self._run_button.enabled, self._cancel_button.enabled = True, False
        self._progress_bar.visible = False
