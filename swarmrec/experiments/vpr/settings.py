"""What one run of full-image place recognition through a swarm is (``swarmrec run --method``)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from swarmrec.errors import ConfigError
from swarmrec.experiments.places.settings import PlacesSettings
from swarmrec.services.settings import VprSettings

__all__ = ["METHODS", "DvprSettings", "Method", "VprRunSettings"]

Method = Literal["constellations", "dvpr", "both"]
METHODS: tuple[str, ...] = ("constellations", "dvpr", "both")


@dataclass(frozen=True)
class DvprSettings:
    """The full-image method's own choices (the services' :class:`VprSettings`)."""

    #: Clusters each robot owns (the paper's c); k = robots x c centres.
    clusters_per_robot: int = 1
    #: Seed of the paper's random assignment of clusters to robots.
    assignment_seed: int = 0
    #: How queries carry descriptors to their owner: int8 (4 + d bytes) or float32 (4 d).
    wire_code: str = "int8"
    #: Centres file (.npz, one array per k); None: the shipped ones, or trained for this run.
    centres: Path | None = None
    #: An assignment table (JSON) instead of the seeded random one.
    assignment: Path | None = None
    #: The descriptor's ONNX model; empty: the project's own.
    descriptor_model: str = ""
    #: onnxruntime threads of each detector's descriptor.
    descriptor_threads: int = 1
    #: Lock-step steps between live re-balancings of the cluster owners (0: none; docs/vpr.md,
    #: "Re-balancing a live swarm"): the job asks the coordinator after every this many steps.
    rebalance_every: int = 0

    def __post_init__(self) -> None:
        if self.rebalance_every < 0:
            raise ConfigError(f"rebalance_every must be >= 0 steps (0: none), got {self.rebalance_every}")
        self.component(None)

    def component(self, centres: Path | None) -> VprSettings:
        """The services' settings (validated), with the centres file the run resolved."""
        return VprSettings(
            place_method="dvpr",
            descriptor_model=self.descriptor_model,
            descriptor_threads=self.descriptor_threads,
            vpr_centres=str(centres) if centres else "",
            vpr_clusters_per_robot=self.clusters_per_robot,
            vpr_assignment_seed=self.assignment_seed,
            vpr_assignment=self.assignment,
            vpr_wire_code=self.wire_code,  # type: ignore[arg-type]  # checked by VprSettings
        )


@dataclass(frozen=True)
class VprRunSettings:
    """A run of ``--method dvpr`` (or ``both``): ``run`` holds what every method shares (the
    data, robots, pace, output folder, the swarm's name, security, hosting, pixels)."""

    run: PlacesSettings = field(default_factory=PlacesSettings)
    dvpr: DvprSettings = field(default_factory=DvprSettings)
    #: "dvpr", or "both": the constellation method too, on the same frames, and side by side.
    method: Method = "dvpr"

    def __post_init__(self) -> None:
        if self.method not in ("dvpr", "both"):
            raise ConfigError(f"the full-image pipeline runs method dvpr or both, got {self.method!r}")
        if not self.run.pixels.enabled:
            raise ConfigError(
                "--method dvpr describes camera images, and a constellation dataset has none: add "
                "--from-pixels (the synthetic world rendered as RGB-D frames) or --rgbd DIR (a recording)"
            )
        if self.run.robots < 2:
            raise ConfigError("full-image place recognition matches other robots' frames: --robots 2 or more")
        if self.dvpr.rebalance_every and not self.run.lockstep:
            raise ConfigError(
                "--rebalance-every counts lock-step steps: use it with --pace lockstep (a free-running "
                "swarm re-balances on its own timer, the place-owners' vpr_rebalance_every_s)"
            )

    @property
    def out(self) -> Path:
        return self.run.out

    def with_(self, **changes: Any) -> VprRunSettings:
        return replace(self, **changes)
