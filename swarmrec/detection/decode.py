"""Decoding of YOLO-style ONNX outputs into candidate boxes.

The two layouts exported models use:

* ``v5``: ``[1, N, 5 + C]`` per box ``cx cy w h objectness class scores``
  (YOLOv3/v5/v7 exports); confidence = objectness x best class score.
* ``v8``: ``[1, 4 + C, N]`` per box ``cx cy w h class scores``, no
  objectness (YOLOv8/v11 exports); confidence = best class score.

Boxes are in model input pixels. Each box keeps its single best class, as
YOLOv5's and Ultralytics' default (not multi-label) post-processing does.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from swarmrec.detection.errors import OutputLayoutError

__all__ = ["Candidates", "Layout", "decode_output", "detect_layout"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class Layout(StrEnum):
    """Which way a YOLO model lays out its output."""

    V5 = "v5"
    V8 = "v8"


@dataclass(frozen=True, eq=False)
class Candidates:
    """Every box of one image before thresholding and NMS.

    ``boxes[i]`` is ``x1 y1 x2 y2`` in model input pixels, with confidence
    ``scores[i]`` for class ``class_ids[i]``.
    """

    boxes: FloatArray
    scores: FloatArray
    class_ids: IntArray

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 4)
        scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        class_ids = np.asarray(self.class_ids, dtype=np.int64).reshape(-1)
        if not boxes.shape[0] == scores.shape[0] == class_ids.shape[0]:
            raise ValueError(
                f"{boxes.shape[0]} boxes, {scores.shape[0]} scores and {class_ids.shape[0]} class ids"
            )
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "scores", scores)
        object.__setattr__(self, "class_ids", class_ids)

    def __len__(self) -> int:
        return int(self.scores.shape[0])


def detect_layout(shape: tuple[int, ...], n_classes: int, layout: Layout | None = None) -> Layout:
    """The layout of an output of ``shape`` for ``n_classes`` classes.

    With ``layout`` given, the shape is only checked against it. Without, the
    shape must fit exactly one layout: ``[1, 4 + C, 5 + C]`` fits both
    (``4 + C`` v5 boxes or ``5 + C`` v8 boxes), and then only the caller knows.
    """
    if n_classes < 1:
        raise OutputLayoutError(shape, n_classes, "the number of classes must be at least 1")
    if len(shape) != 3 or shape[0] != 1:
        raise OutputLayoutError(shape, n_classes, "expected a batch of one, [1, N, 5 + C] or [1, 4 + C, N]")
    fits = {
        Layout.V5: shape[2] == 5 + n_classes and shape[1] > 0,
        Layout.V8: shape[1] == 4 + n_classes and shape[2] > 0,
    }
    if layout is not None:
        if not fits[layout]:
            want = f"[1, N, {5 + n_classes}]" if layout is Layout.V5 else f"[1, {4 + n_classes}, N]"
            raise OutputLayoutError(shape, n_classes, f"the {layout.value} layout needs {want}")
        return layout
    matching = [candidate for candidate, ok in fits.items() if ok]
    if not matching:
        raise OutputLayoutError(
            shape,
            n_classes,
            f"fits neither [1, N, {5 + n_classes}] (v5) nor [1, {4 + n_classes}, N] (v8); "
            "is the number of classes right?",
        )
    if len(matching) > 1:
        raise OutputLayoutError(shape, n_classes, "fits both v5 and v8 layouts; set the layout explicitly")
    return matching[0]


def decode_output(output: npt.ArrayLike, n_classes: int, layout: Layout | None = None) -> Candidates:
    """All boxes of a ``[1, N, 5 + C]`` (v5) or ``[1, 4 + C, N]`` (v8) output, unfiltered.

    The layout is detected from the shape unless given (see :func:`detect_layout`).
    """
    out = np.asarray(output)
    chosen = detect_layout(tuple(int(d) for d in out.shape), n_classes, layout)
    # Rows are fields (cx, cy, w, h, ...) in both cases, so the v8 output needs no transposed copy.
    fields = out[0].T if chosen is Layout.V5 else out[0]
    class_scores = fields[5:] if chosen is Layout.V5 else fields[4:]
    class_ids = np.argmax(class_scores, axis=0)
    scores = np.take_along_axis(class_scores, class_ids[None, :], axis=0)[0].astype(np.float64)
    if chosen is Layout.V5:
        # The class is the best class score; it is also the best product whenever objectness > 0.
        scores *= fields[4]
    cx, cy, w, h = (fields[i].astype(np.float64) for i in range(4))
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    return Candidates(boxes, scores, class_ids.astype(np.int64))
