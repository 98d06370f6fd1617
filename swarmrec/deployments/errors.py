"""What a deployment raises (apart from the base module so that its helpers, such as the
link emulator, can raise it while the base module uses them)."""

from __future__ import annotations

from swarmrec.errors import SwarmrecError

__all__ = ["DeploymentError", "SwarmStartError"]


class DeploymentError(SwarmrecError):
    """A deployment could not start, reach or stop its swarm."""


class SwarmStartError(DeploymentError):
    """A service process exited or never became ready."""
