"""Vision: what the UAVs see and what is made of it.

* :class:`Camera` (``camera``): nadir images rendered with Mitsuba 3 from the radio's 3D scene.
* :class:`ImageLink` (``image-link``): the images as received over the UE's link (packet loss).
* :class:`PersonDetector` (``person-detector``): people in the received images, with
  their estimated ground positions; trained by ``python -m caviar_plugins.tools.training.train_detector``,
  or with ``model = "yolo"`` a YOLO trained on the twin's own frames
  (``python -m caviar_plugins.tools.training.train_yolo``, :mod:`~caviar_plugins.tools.training.twin_frames`), run from
  ONNX by :class:`YoloOnnx` (any YOLOv8/YOLO11-style file).
"""

from caviar_plugins.vision.camera import Camera, VisualConfig, VisualScene, default_targets
from caviar_plugins.vision.image_link import ImageLink, loss_for_throughput, packet_loss, psnr
from caviar_plugins.vision.person_detector import (
    OnnxPixelModel,
    PersonDetector,
    PixelDetector,
    builtin_model,
    export_onnx,
    pixel_to_ground,
)
from caviar_plugins.vision.yolo import YoloOnnx

__all__ = ["Camera", "ImageLink", "OnnxPixelModel", "PersonDetector", "PixelDetector", "VisualConfig", "VisualScene",
           "builtin_model", "default_targets", "export_onnx", "loss_for_throughput", "packet_loss",
           "pixel_to_ground", "psnr", "YoloOnnx"]
