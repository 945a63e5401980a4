"""Which runtime runs the person detector's model: the model's own on the CPU (onnxruntime,
scikit-learn) or torch on its device (:mod:`~caviar_plugins.vision.onnx_torch` for YOLO,
:mod:`~caviar_plugins.vision.forest_torch` for the pixel forests), from the plugin's
``runtime`` and ``device`` (:func:`caviar_plugins.vision.yolo.choose_runtime`)."""

from __future__ import annotations

from caviar_plugins.vision.forest_torch import unsupported
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
    explicit = p.runtime == "torch"  # (auto takes torch for the project's own models only)
    if p.model == "yolo" or (p.model.endswith(".onnx") and p.model not in BUILTIN):
        path = BUILTIN_YOLO if p.model == "yolo" else ctx.resolve(p.model)
        if runtime == "torch" and p.model == "yolo":  # (the builtin model takes images)
            return YoloPersonDetector(YoloOnnx(path, p.confidence, p.iou, p.person_class, runtime="torch",
                                               device=p.device))
        session = onnx_session(path, p.workers)  # loaded once, whichever kind of model it is
        if takes_images(session):
            return YoloPersonDetector(YoloOnnx(path, p.confidence, p.iou, p.person_class, session=session,
                                               runtime="torch" if explicit else "onnxruntime", device=p.device))
        if explicit:
            raise ValueError(f"params.runtime = 'torch': {path} is an ONNX pixel classifier; it runs with "
                             "onnxruntime")
        return PixelDetector(OnnxPixelModel(path, session))
    forest = builtin_model(BUILTIN[p.model]) if p.model in BUILTIN else PixelDetector.load(ctx.resolve(p.model))
    why = unsupported(forest.forest)
    if runtime == "torch" and why is None:
        forest.to_device(torch_device_of(p.device))
    elif explicit:
        raise ValueError(f"params.runtime = 'torch': {p.model}: the pixel model is {why}; it runs with scikit-learn")
    return forest

