"""Letterboxing: fit an image into the model's input without distorting it.

YOLO models are trained on letterboxed images (aspect kept, grey 114
borders), so feeding a stretched image would shift every box. The
:class:`Letterbox` returned with the padded image is what maps the model's
boxes back to pixels of the original image.

Coordinates are continuous pixel coordinates with pixel ``i`` covering
``[i, i + 1)``, the convention of ``cv2.resize`` and of YOLO's boxes; so a
resize by ``new / old`` maps coordinates by exactly that ratio.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.detection.errors import DetectionError

__all__ = ["PAD_VALUE", "Letterbox", "letterbox"]

FloatArray = npt.NDArray[np.float64]
ImageArray = npt.NDArray[np.uint8]

#: The grey YOLO pads with during training, so padding looks like "nothing" to the model.
PAD_VALUE = 114


@dataclass(frozen=True)
class Letterbox:
    """How an image was placed in the model input: ``model = original * scale + pad``.

    The two scales differ slightly when the resized size was rounded to whole
    pixels; keeping both makes the inverse exact for the resize that was done.
    """

    scale_x: float
    scale_y: float
    pad_x: int
    pad_y: int
    width: int
    height: int

    def to_original(self, boxes: npt.ArrayLike) -> FloatArray:
        """Boxes ``x1 y1 x2 y2`` (``n x 4``) in model input pixels -> original image pixels, clipped.

        Clipping to the image keeps boxes that reach into the padding from
        pointing at pixels that do not exist.
        """
        b = np.array(boxes, dtype=np.float64).reshape(-1, 4)
        b[:, 0::2] = np.clip((b[:, 0::2] - self.pad_x) / self.scale_x, 0.0, self.width)
        b[:, 1::2] = np.clip((b[:, 1::2] - self.pad_y) / self.scale_y, 0.0, self.height)
        return b


def letterbox(image: ImageArray, input_hw: tuple[int, int]) -> tuple[ImageArray, Letterbox]:
    """Resize ``image`` (``h x w x c``) to fit ``input_hw`` keeping its aspect, pad the rest with grey.

    The image is centred; an odd padding puts the extra pixel at the bottom or
    right, as YOLOv5's letterbox does, so boxes agree with models trained there.
    """
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise DetectionError(f"expected an image of shape (h, w, channels), got {image.shape}")
    out_h, out_w = input_hw
    h, w = image.shape[:2]
    gain = min(out_h / h, out_w / w)
    new_w = min(out_w, max(1, round(w * gain)))
    new_h = min(out_h, max(1, round(h * gain)))
    resized = (
        image
        if (new_w, new_h) == (w, h)
        else cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    )
    left = (out_w - new_w) // 2
    top = (out_h - new_h) // 2
    padded = cv2.copyMakeBorder(
        resized,
        top,
        out_h - new_h - top,
        left,
        out_w - new_w - left,
        cv2.BORDER_CONSTANT,
        value=(PAD_VALUE,) * image.shape[2],
    )
    # copyMakeBorder drops a trailing channel axis of 1; the model input needs it.
    padded = padded.reshape(out_h, out_w, image.shape[2])
    return cast(ImageArray, padded), Letterbox(new_w / w, new_h / h, left, top, w, h)
