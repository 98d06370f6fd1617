"""Train the k-means centres that split the descriptor space, on other worlds than a swarm's.

The paper clusters NetVLAD descriptors of Oxford RobotCar and deploys on KITTI: the centres
must come from more general data than the deployment's. Here the "other" data are *varied*
offices (:mod:`swarmrec.vpr.data`: other seeds, desk counts, orbits, heights, glances),
never the default office of a deployment seed. The shipped ``models/descriptor/centres.npz``
holds one array per k (``k10``, ``k20``, ...) and a JSON ``meta`` string saying how they were
made; any other k (k = robots x clusters per robot) is one command::

    python -m swarmrec.vpr.centres --ks 20 40 160 --out models/descriptor/centres.npz

Rendering the 8 other worlds (625 frames each) and describing them takes about a minute on
one core; k-means itself well under a second per k.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.vpr.clusters import save_centres, train_centres
from swarmrec.vpr.data import render_world
from swarmrec.vpr.index import set_faiss_threads
from swarmrec.vpr.model import DescriptorModel

__all__ = ["CentresSettings", "CentresSummary", "main", "other_descriptors"]

Float32Array = npt.NDArray[np.float32]

#: Frames of each other world (the default office's length) before the stride.
OTHER_WORLD_FRAMES = 2500


def other_descriptors(
    model: DescriptorModel, worlds: int, seed_base: int, stride: int
) -> tuple[Float32Array, list[int]]:
    """Descriptors of every ``stride``-th frame of the varied worlds ``seed_base + j``, and the seeds."""
    seeds = [seed_base + j for j in range(worlds)]
    parts = []
    for seed in seeds:
        world = render_world(seed, OTHER_WORLD_FRAMES, stride, vary=True)
        parts.append(model.describe(world.images))
    return np.concatenate(parts), seeds


@dataclass(frozen=True)
class CentresSettings:
    out: Path
    model: Path | None = None
    ks: tuple[int, ...] = (10, 20, 40, 80, 160)
    worlds: int = 8
    seed_base: int = 14_000
    stride: int = 4
    seed: int = 0
    threads: int = 1

    def __post_init__(self) -> None:
        if not self.ks or min(self.ks) < 1:
            raise ConfigError(f"ks must be >= 1, got {self.ks}")
        for name in ("worlds", "stride", "threads"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if max(self.ks) > self.worlds * (OTHER_WORLD_FRAMES // self.stride):
            raise ConfigError(f"k={max(self.ks)} needs more descriptors: raise worlds or lower stride")


@dataclass(frozen=True)
class CentresSummary:
    path: Path
    ks: tuple[int, ...]
    descriptors: int
    seconds: float


def main(settings: CentresSettings) -> CentresSummary:
    started = time.perf_counter()
    s = settings
    set_faiss_threads(s.threads)
    model = DescriptorModel(s.model, intra_op_threads=s.threads)
    other, seeds = other_descriptors(model, s.worlds, s.seed_base, s.stride)
    centres = {k: train_centres(other, k, s.seed) for k in s.ks}
    meta = {
        "what": "k-means centres of the place descriptor, trained on varied office worlds",
        "model": Path(model.model).name,
        "worlds": seeds,
        "stride": s.stride,
        "descriptors": len(other),
        "seed": s.seed,
        "command": f"python -m swarmrec.vpr.centres --ks {' '.join(map(str, s.ks))}",
    }
    Path(s.out).parent.mkdir(parents=True, exist_ok=True)
    save_centres(s.out, centres, meta)
    return CentresSummary(Path(s.out), s.ks, len(other), time.perf_counter() - started)


def _parse_args(argv: Sequence[str] | None) -> CentresSettings:
    d = CentresSettings(out=Path("centres.npz"))
    p = argparse.ArgumentParser(prog="python -m swarmrec.vpr.centres", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the .npz to write (one array per k)")
    p.add_argument("--model", type=Path, help="descriptor ONNX (default: the shipped model)")
    p.add_argument("--ks", type=int, nargs="+", default=list(d.ks), help="numbers of centres")
    p.add_argument("--worlds", type=int, default=d.worlds, help="varied office worlds to describe")
    p.add_argument("--seed-base", type=int, default=d.seed_base, help="their seeds are seed-base + j")
    p.add_argument("--stride", type=int, default=d.stride, help="describe every n-th frame")
    p.add_argument("--seed", type=int, default=d.seed, help="k-means seed")
    a = p.parse_args(argv)
    return CentresSettings(a.out, a.model, tuple(a.ks), a.worlds, a.seed_base, a.stride, a.seed)


if __name__ == "__main__":
    try:
        summary = main(_parse_args(sys.argv[1:]))
    except ConfigError as exc:
        sys.exit(f"error: {exc}")
    print(f"{len(summary.ks)} sets of centres from {summary.descriptors} descriptors -> {summary.path}")
