"""The built-in synthetic office world: the project's default dataset, no download.

A handheld camera circles a block of desks covered with COCO objects; a
simulated detector turns each frame into a noisy constellation. See
docs/synthetic-world.md for how it is built and how it compares with the real
TUM sequence; :mod:`swarmrec.synthetic.stats` computes and compares the
statistics of any constellation sequence (``python -m swarmrec.synthetic.stats``).

>>> from swarmrec.synthetic import OfficeConfig, generate_office
>>> ds = generate_office(OfficeConfig.preset("easy", seed=1))
>>> len(ds.sequence) == len(ds.noise_free) == len(ds.trajectory) == 600
True
"""

from swarmrec.synthetic.camera import (
    TUM_FR3_CAMERA,
    PinholeCamera,
    matrices_to_quaternions,
    quaternions_to_matrices,
)
from swarmrec.synthetic.config import PRESETS, OfficeConfig
from swarmrec.synthetic.labels import coco_names, label_index
from swarmrec.synthetic.office import (
    SEQUENCE_NAME,
    SyntheticDataset,
    covisibility,
    generate_office,
    write_dataset,
)
from swarmrec.synthetic.world import OfficeWorld

__all__ = [
    "PRESETS",
    "SEQUENCE_NAME",
    "TUM_FR3_CAMERA",
    "OfficeConfig",
    "OfficeWorld",
    "PinholeCamera",
    "SyntheticDataset",
    "coco_names",
    "covisibility",
    "generate_office",
    "label_index",
    "matrices_to_quaternions",
    "quaternions_to_matrices",
    "write_dataset",
]
