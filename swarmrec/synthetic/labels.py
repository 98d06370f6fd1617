"""The 80 COCO class names the synthetic world (and the paper) label objects with.

The list is bundled in the package (``swarmrec/data/coco.names``) so the
built-in dataset works on a machine without the shared data folder. The line
index is the label index; the spellings are YOLO's (``tvmonitor``,
``diningtable``, ``pottedplant``, ``sofa``, ``motorbike``, ``aeroplane``).
"""

from __future__ import annotations

from functools import cache

from swarmrec.datasets.labels import COCO_NAMES

__all__ = ["coco_names", "label_index"]

N_COCO_LABELS = 80


def coco_names() -> tuple[str, ...]:
    """The 80 COCO class names, in label-index order (the package's bundled list)."""
    if len(COCO_NAMES) != N_COCO_LABELS:
        # A packaging mistake, not a user error: fail loudly at first use.
        raise RuntimeError(f"bundled coco.names has {len(COCO_NAMES)} names, expected {N_COCO_LABELS}")
    return COCO_NAMES


@cache
def _index() -> dict[str, int]:
    return {name: i for i, name in enumerate(coco_names())}


def label_index(name: str) -> int:
    """The label index of a COCO class name (``KeyError`` if it is not one)."""
    return _index()[name]
