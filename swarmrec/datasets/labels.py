"""Label lists: one class name a line, the line index is the label index."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from swarmrec.errors import ConfigError, DatasetError

__all__ = ["COCO_NAMES", "LabelMap", "builtin_coco_names", "label_names", "read_label_names"]


def read_label_names(path: str | Path) -> tuple[str, ...]:
    """Read a label list (e.g. coco.names).

    Blank lines at the end of the file are tolerated; a blank line in the
    middle would shift every later index, so it is an error.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DatasetError(path, f"cannot read label list: {exc.strerror or exc}") from exc
    lines = [line.strip() for line in text.splitlines()]
    while lines and not lines[-1]:
        lines.pop()
    return _validate_names(lines, str(path))


def _validate_names(lines: list[str], source: str) -> tuple[str, ...]:
    if not lines:
        raise DatasetError(source, "label list is empty")
    seen: dict[str, int] = {}
    for number, name in enumerate(lines, start=1):
        if not name:
            raise DatasetError(source, "blank line inside the label list", line=number)
        if name in seen:
            raise DatasetError(source, f"label {name!r} repeats the one on line {seen[name]}", line=number)
        seen[name] = number
    return tuple(lines)


def builtin_coco_names() -> tuple[str, ...]:
    """The 80 COCO class names (YOLO spelling) bundled with the package."""
    text = resources.files("swarmrec").joinpath("data/coco.names").read_text(encoding="utf-8")
    return _validate_names([line.strip() for line in text.splitlines() if line.strip()], "coco")


COCO_NAMES: tuple[str, ...] = builtin_coco_names()


def label_names(path: str | Path | None = None, n_labels: int | None = None) -> tuple[str, ...]:
    """The label list in ``path``, the 80 COCO names when it is None; checked to have
    ``n_labels`` labels when given (a swarm's members must agree on their label list)."""
    names = read_label_names(path) if path else COCO_NAMES
    if n_labels is not None and len(names) != n_labels:
        where = path or "the COCO list"
        raise ConfigError(f"the label list ({where}) has {len(names)} labels, the swarm {n_labels}")
    return names


class LabelMap:
    """Name <-> index lookup for one label list."""

    def __init__(self, names: tuple[str, ...]) -> None:
        self.names = names
        self._index = {name: i for i, name in enumerate(names)}

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int | None:
        """The label index of ``name``, or None when it is not in the list."""
        return self._index.get(name)
