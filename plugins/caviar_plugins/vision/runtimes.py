"""Which runtime runs the person detector's model: the model's own on the CPU (onnxruntime,
scikit-learn) or torch on its device (:mod:`~caviar_plugins.vision.onnx_torch` for YOLO,
:mod:`~caviar_plugins.vision.forest_torch` for the pixel forests), from the plugin's
``runtime`` and ``device`` (:func:`caviar_plugins.vision.yolo.choose_runtime`)."""

from __future__ import annotations

from caviar_plugins.vision.pixel_detector import (
    BUILTIN,
    OnnxPixelModel,
    PixelDetector,
    YoloPersonDetector,
    builtin_model,
)
from caviar_plugins.vision.yolo import BUILTIN_YOLO, YoloOnnx, onnx_session, takes_images, torch_device_of


def detector_model(ctx, runtime: str) -> PixelDetector | YoloPersonDetector:
    """The person detector's model for its ``ctx.params`` (``model``, ``runtime``, ``device``...)
    on ``runtime`` (``torch``, or the model's CPU runtime)."""
    p = ctx.params
    if p.model == "yolo" or (p.model.endswith(".onnx") and p.model not in BUILTIN):
        path = BUILTIN_YOLO if p.model == "yolo" else ctx.resolve(p.model)
        if runtime == "torch" and p.model == "yolo":  # (the builtin model takes images)
            return YoloPersonDetector(YoloOnnx(path, p.confidence, p.iou, p.person_class, runtime="torch",
                                               device=p.device))
        session = onnx_session(path, p.workers)  # loaded once, whichever kind of model it is
        if takes_images(session):
            return YoloPersonDetector(YoloOnnx(path, p.confidence, p.iou, p.person_class, session=session,
                                               runtime=runtime, device=p.device))
        if p.runtime == "torch":
            raise ValueError(f"params.runtime = 'torch': {path} is an ONNX pixel classifier; it runs with "
                             "onnxruntime")
        return PixelDetector(OnnxPixelModel(path, session))
    forest = builtin_model(BUILTIN[p.model]) if p.model in BUILTIN else PixelDetector.load(ctx.resolve(p.model))
    is_forest = getattr(forest.forest, "estimators_", None) is not None
    if runtime == "torch" and (is_forest or p.runtime == "torch"):  # (auto: a forest only)
        try:
            forest.to_device(torch_device_of(p.device))
        except ValueError as e:
            raise ValueError(f"params.{e}") from None
    return forest
