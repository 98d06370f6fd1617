"""Where a swarm runs: one small interface, one implementation per place.

* :class:`~swarmrec.deployments.local.LocalDeployment`: every service a process on
  this machine (no container engine needed);
* :class:`~swarmrec.deployments.compose.ComposeDeployment`: a compose project's
  containers, with a real Prometheus (``swarmrec compose up``).

Each takes a :class:`~swarmrec.deployments.base.SwarmSpec` (bus settings, each
robot's service kinds from the registry, shared settings) and implements
:class:`~swarmrec.deployments.base.Deployment`. Experiments take a deployment and
never know which one it is.
"""

from swarmrec.deployments.base import Deployment, DeploymentError, SwarmSpec, SwarmStartError
from swarmrec.deployments.compose import ComposeDeployment, ComposeError
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import Scrape

__all__ = [
    "ComposeDeployment",
    "ComposeError",
    "Deployment",
    "DeploymentError",
    "LocalDeployment",
    "Scrape",
    "SwarmSpec",
    "SwarmStartError",
]
