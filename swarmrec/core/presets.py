"""Named parameter sets for place recognition.

``paper`` reproduces the published evaluation of the constellation paper
exactly (see ``../shared/papers/REFERENCE_NOTES.md``). Other presets are
improvements and say what they change; the paper preset never moves.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from swarmrec.core.ranges import RangeStrategy
from swarmrec.errors import ConfigError

__all__ = ["PRESETS", "Preset", "get_preset"]


@dataclass(frozen=True)
class Preset:
    """Every knob of constellation place recognition."""

    name: str
    #: Frames with fewer objects are ignored (never scored against anything).
    min_objects: int = 3
    #: Pairs with |i - j| <= exclusion are never loop-closure candidates.
    exclusion: int = 100
    #: Data-association threshold d on surroundings-vector distance (metres).
    d: float = 0.25
    #: Fewer common objects than this: no data association, score 0.
    min_common: int = 3
    #: Candidates each range holder returns (n_ret).
    n_ret: int = 4
    #: Robots further queried with the full constellation (n_fq), plus the querying robot.
    n_fq: int = 4
    #: Restrict the association's nearest-vector search to the same label (Eq. 3 as written).
    same_label_only: bool = False
    #: How label ranges are assigned to holders.
    ranges: RangeStrategy = "even"

    def __post_init__(self) -> None:
        problems = []
        if self.min_objects < 0:
            problems.append(f"min_objects must be >= 0, got {self.min_objects}")
        if self.exclusion < 0:
            problems.append(f"exclusion must be >= 0, got {self.exclusion}")
        if not self.d > 0:
            problems.append(f"d must be > 0 metres, got {self.d}")
        if self.min_common < 1:
            problems.append(f"min_common must be >= 1, got {self.min_common}")
        if self.n_ret < 1:
            problems.append(f"n_ret must be >= 1, got {self.n_ret}")
        if self.n_fq < 0:
            problems.append(f"n_fq must be >= 0, got {self.n_fq}")
        if self.ranges not in ("even", "balanced"):
            problems.append(f"ranges must be 'even' or 'balanced', got {self.ranges!r}")

        if problems:
            raise ConfigError(f"preset {self.name!r}: " + "; ".join(problems))

    def with_(self, **changes: object) -> Preset:
        """A copy with some knobs changed (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]


PRESETS: dict[str, Preset] = {
    # The published evaluation, exactly: min 3 objects, 100-frame exclusion,
    # d = 0.25 m, n_ret = n_fq = 4, cross-label association search, even ranges.
    "paper": Preset(name="paper"),
    # Eq. 3 as the paper writes it (same-label search) and label ranges balanced
    # on label frequencies, which spreads the shard load the paper found uneven.
    "balanced": Preset(name="balanced", same_label_only=True, ranges="balanced"),
}


def get_preset(name: str) -> Preset:
    """The preset called ``name``; a clear error lists the known ones."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; known presets: {', '.join(sorted(PRESETS))}") from None
