"""swarmrec: decentralized place and landmark recognition for robot swarms."""

__version__ = "0.1.0"
