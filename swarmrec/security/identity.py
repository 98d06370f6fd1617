"""Who is who on the swarm's links: one identity per certificate.

The router's access control can only tell connections apart by the common
name (CN) of the certificate each one presented, so the CN carries
everything a rule needs, and nothing else:

    r<robot>.<kind>.<swarm>      a robot's service        r3.index-shard.lab
    r<first>-<last>.host.<swarm> a process hosting every service of robots first..last
                                 (r3.host.lab for one robot: robot hosting)
    client.<name>.<swarm>        a read-only client       client.cli.lab
    operator.<name>.<swarm>      a client that also drives replay (detector step/replay/classify)
    router.<swarm>               the router (one per swarm: the star topology)
    r<robot>.router.<swarm>      robot <robot>'s own router (the mesh topology, docs/mesh.md)

Dots separate the parts because no part can hold one: swarm names are one
key segment of ``[A-Za-z0-9_-]`` (swarmrec.runtime.keys), kinds are the
registry's names and client names are restricted to ``[a-z0-9-]`` here. The
swarm is part of every CN so a certificate of one swarm never matches a rule
of another, even when both swarms share a CA by mistake.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from swarmrec.errors import ConfigError
from swarmrec.runtime import keys
from swarmrec.services import registry

__all__ = ["SERVICE_KINDS", "Identity", "Role", "parse_common_name"]

Role = Literal["service", "host", "client", "operator", "router"]

#: The kinds a robot runs (the registry's built-in per-robot kinds); the router is an identity
#: of its own. Kinds a plugin registers later are valid identities too.
SERVICE_KINDS: tuple[str, ...] = registry.kinds("robot")

_NAME = re.compile(r"^[a-z0-9](?:[a-z0-9-]{0,30}[a-z0-9])?$")
_ROBOT = re.compile(r"^r(0|[1-9][0-9]{0,5})$")
_ROBOTS = re.compile(r"^r(0|[1-9][0-9]{0,5})(?:-(0|[1-9][0-9]{0,5}))?$")
MAX_ROBOT = 999_999
#: X.509's upper bound on a common name (RFC 5280 ub-common-name).
MAX_COMMON_NAME = 64


@dataclass(frozen=True)
class Identity:
    """One certificate's owner. Build with :meth:`service`, :meth:`client`,
    :meth:`operator` or :meth:`router`; the fields are validated either way."""

    swarm: str
    role: Role
    kind: str = ""
    robot: int = -1
    name: str = ""
    #: A host's last robot (its first is ``robot``).
    last: int = -1

    def __post_init__(self) -> None:
        keys.validate_swarm_name(self.swarm)
        self._check_role()
        if len(self.common_name) > MAX_COMMON_NAME:
            raise ConfigError(
                f"common name {self.common_name!r} is {len(self.common_name)} characters, X.509 allows "
                f"{MAX_COMMON_NAME}: use a shorter swarm (or client) name"
            )

    def _check_role(self) -> None:
        if self.role == "service":
            # Read now, not at import: kinds installed by plugins (entry points) count too.
            known = registry.kinds("robot")
            if self.kind not in known:
                raise ConfigError(f"service kind must be one of {known}, got {self.kind!r}")
            if not 0 <= self.robot <= MAX_ROBOT:
                raise ConfigError(f"robot id must be 0..{MAX_ROBOT}, got {self.robot}")
            if self.name or self.last != -1:
                raise ConfigError("a service identity has no name, only a kind and a robot")
        elif self.role == "host":
            if not 0 <= self.robot <= self.last <= MAX_ROBOT:
                raise ConfigError(
                    f"a host's robots must be first..last within 0..{MAX_ROBOT}, "
                    f"got {self.robot}..{self.last}"
                )
            if self.kind or self.name:
                raise ConfigError("a host identity has only its robots")
        elif self.role in ("client", "operator"):
            if not _NAME.fullmatch(self.name):
                raise ConfigError(
                    f"{self.role} name must be 1-32 of a-z 0-9 - (not starting or ending with -), "
                    f"got {self.name!r}"
                )
            if self.kind or self.robot != -1 or self.last != -1:
                raise ConfigError(f"a {self.role} identity has a name, not a kind or a robot")
        elif self.role == "router":
            if self.kind or self.name or self.last != -1 or not -1 <= self.robot <= MAX_ROBOT:
                raise ConfigError("a router identity has only a swarm, and a robot for a robot's own router")
        else:
            raise ConfigError(f"unknown role {self.role!r}")

    @classmethod
    def service(cls, swarm: str, kind: str, robot: int) -> Identity:
        return cls(swarm, "service", kind=kind, robot=robot)

    @classmethod
    def host(cls, swarm: str, first: int, last: int | None = None) -> Identity:
        """A process hosting every service of robots ``first``..``last`` (one robot by default)."""
        return cls(swarm, "host", robot=first, last=first if last is None else last)

    @property
    def robots(self) -> range:
        """The robots whose services this identity may act as (none for clients and the router)."""
        if self.role == "service":
            return range(self.robot, self.robot + 1)
        if self.role == "host":
            return range(self.robot, self.last + 1)
        return range(0)

    @classmethod
    def client(cls, swarm: str, name: str) -> Identity:
        return cls(swarm, "client", name=name)

    @classmethod
    def operator(cls, swarm: str, name: str) -> Identity:
        return cls(swarm, "operator", name=name)

    @classmethod
    def router(cls, swarm: str, robot: int = -1) -> Identity:
        """The swarm's one router (``robot`` -1, the star), or ``robot``'s own (the mesh)."""
        return cls(swarm, "router", robot=robot)

    @property
    def common_name(self) -> str:
        if self.role == "service":
            return f"r{self.robot}.{self.kind}.{self.swarm}"
        if self.role == "host":
            span = f"r{self.robot}" if self.last == self.robot else f"r{self.robot}-{self.last}"
            return f"{span}.host.{self.swarm}"
        if self.role == "router":
            return f"router.{self.swarm}" if self.robot < 0 else f"r{self.robot}.router.{self.swarm}"
        return f"{self.role}.{self.name}.{self.swarm}"

    def __str__(self) -> str:
        return self.common_name


def parse_common_name(cn: str) -> Identity:
    """The identity a CN names; ConfigError for anything outside the scheme."""
    parts = cn.split(".")
    if len(parts) == 2 and parts[0] == "router":
        return Identity.router(parts[1])
    if len(parts) == 3:
        first, middle, swarm = parts
        if first in ("client", "operator"):
            return Identity(swarm, "client" if first == "client" else "operator", name=middle)
        if middle == "host":
            span = _ROBOTS.fullmatch(first)
            if span:
                lo = int(span.group(1))
                return Identity.host(swarm, lo, int(span.group(2)) if span.group(2) else lo)
        robot = _ROBOT.fullmatch(first)
        if robot and middle == "router":
            return Identity.router(swarm, int(robot.group(1)))
        if robot:
            return Identity.service(swarm, middle, int(robot.group(1)))
    raise ConfigError(
        f"{cn!r} is not a swarmrec common name "
        "(r<robot>.<kind>.<swarm>, r<first>-<last>.host.<swarm>, client.<name>.<swarm>, "
        "operator.<name>.<swarm>, router.<swarm>, r<robot>.router.<swarm>)"
    )
