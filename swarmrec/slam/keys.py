"""Variable keys: gtsam Symbols, one character per robot.

A key is a 64-bit unsigned integer laid out as gtsam's ``Symbol``: the
character in the top 8 bits, the index in the low 56 bits (``Symbol('a', 5)``
is ``0x61 << 56 | 5``). The multi-robot convention of the distributed
Gauss-Seidel data sets: robot 0's poses are ``'a'``, robot 1's ``'b'``, ...;
the objects a robot maps get the upper-case letter of their robot (``'A'`` for
robot 0), so both belong to the same robot when the team is partitioned.
"""

from __future__ import annotations

import string

__all__ = [
    "INDEX_BITS",
    "MAX_INDEX",
    "MAX_ROBOTS",
    "describe_key",
    "landmark_key",
    "pose_key",
    "robot_char",
    "robot_of_key",
    "symbol_chr",
    "symbol_index",
    "symbol_key",
]

INDEX_BITS = 56
MAX_INDEX = (1 << INDEX_BITS) - 1
MAX_ROBOTS = len(string.ascii_lowercase)


def symbol_key(character: str, index: int) -> int:
    """The key of ``Symbol(character, index)``, equal to gtsam's ``Symbol(c, j).key()``."""
    if len(character) != 1 or not 0 < ord(character) < 256:
        raise ValueError(f"a symbol character is one byte, got {character!r}")
    if not 0 <= index <= MAX_INDEX:
        raise ValueError(f"a symbol index is in [0, 2^56), got {index}")
    return (ord(character) << INDEX_BITS) | index


def symbol_chr(key: int) -> str:
    """The character of a Symbol key (``'\\x00'`` for a plain integer key below 2^56)."""
    return chr(key >> INDEX_BITS)


def symbol_index(key: int) -> int:
    return key & MAX_INDEX


def robot_char(robot: int) -> str:
    """The lower-case character of robot ``robot`` (0 -> ``'a'``)."""
    if not 0 <= robot < MAX_ROBOTS:
        raise ValueError(f"robots are numbered 0..{MAX_ROBOTS - 1}, got {robot}")
    return string.ascii_lowercase[robot]


def pose_key(robot: int, index: int) -> int:
    """The key of robot ``robot``'s ``index``-th pose."""
    return symbol_key(robot_char(robot), index)


def landmark_key(robot: int, index: int) -> int:
    """The key of the ``index``-th object in robot ``robot``'s map (upper-case character)."""
    return symbol_key(robot_char(robot).upper(), index)


def robot_of_key(key: int) -> int | None:
    """The robot a key belongs to (poses and objects alike), or None for a key of no robot."""
    character = symbol_chr(key).lower()
    if len(character) == 1 and character in string.ascii_lowercase:
        return string.ascii_lowercase.index(character)
    return None


def describe_key(key: int) -> str:
    """``a12`` for a Symbol key, the plain number otherwise (for messages and plots)."""
    character = symbol_chr(key)
    if character.isascii() and character.isalpha():
        return f"{character}{symbol_index(key)}"
    return str(key)
