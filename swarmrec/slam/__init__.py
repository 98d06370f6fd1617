"""Multi-robot object-based SLAM back end: distributed two-stage Gauss-Seidel over pose graphs.

The pure core of Choudhary et al., "Multi Robot Object-based SLAM" (ISER 2016)
and its back end, the two-stage distributed Gauss-Seidel (ICRA 2016). No bus,
no I/O beyond g2o files:

- :mod:`~swarmrec.slam.graph`, :mod:`~swarmrec.slam.keys`, :mod:`~swarmrec.slam.lie`:
  pose graphs partitioned by robot (gtsam Symbol keys), SE(3) helpers;
- :mod:`~swarmrec.slam.g2o`: ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` files, one per robot;
- :mod:`~swarmrec.slam.two_stage`: chordal rotations and the linearised pose step;
- :mod:`~swarmrec.slam.agent`, :mod:`~swarmrec.slam.messages`, :mod:`~swarmrec.slam.dgs`:
  one :class:`DgsAgent` per robot exchanging :class:`DgsMessage`, and the in-process driver;
- :mod:`~swarmrec.slam.centralized`: gtsam's Gauss-Newton / LM reference;
- :mod:`~swarmrec.slam.metrics`: ATE*, ARE*, cost; :mod:`~swarmrec.slam.scenarios`: the
  simulated worlds; :mod:`~swarmrec.slam.alignment`, :mod:`~swarmrec.slam.robust`:
  inter-robot constraints from matched points, and rejecting wrong ones;
- :mod:`~swarmrec.slam.offline`: ``solve_folder`` / ``main``, what ``swarmrec slam`` runs.

>>> from swarmrec.slam import ScenarioSettings, generate_scenario, solve_distributed
>>> scenario = generate_scenario(ScenarioSettings(world="chairs", robots=2, seed=0))
>>> result = solve_distributed(scenario.graph)
>>> result.order, result.converged
((0, 1), True)
"""

from swarmrec.slam.agent import DgsAgent, LocalProblem
from swarmrec.slam.alignment import Alignment, ransac_rigid, rigid_transform
from swarmrec.slam.centralized import CentralizedResult, TwoStageResult, solve_centralized, solve_two_stage
from swarmrec.slam.dgs import (
    DgsSettings,
    DistributedResult,
    StageSummary,
    TraceEntry,
    make_agents,
    run_dgs,
    solve_distributed,
    stage_converged,
)
from swarmrec.slam.errors import (
    AlignmentError,
    G2oError,
    G2oInformationError,
    G2oKeyError,
    G2oQuaternionError,
    GraphError,
    MessageError,
    SlamError,
)
from swarmrec.slam.g2o import RobotFolder, read_g2o, read_robot_folder, write_g2o
from swarmrec.slam.graph import Edge, PoseGraph, is_landmark_key
from swarmrec.slam.keys import landmark_key, pose_key, robot_of_key, symbol_key
from swarmrec.slam.lie import Pose
from swarmrec.slam.messages import FLOATS_PER_ESTIMATE, DgsMessage, StepReport
from swarmrec.slam.metrics import Accuracy, accuracy, are_star, ate_star
from swarmrec.slam.offline import SlamSettings, SolveSummary, main, solve_folder
from swarmrec.slam.ordering import order_robots
from swarmrec.slam.robust import GncResult, PcmResult, PcmSettings, gnc, pcm
from swarmrec.slam.scenarios import PAPER_NOISE_LEVELS, Scenario, ScenarioSettings, generate_scenario

__all__ = [
    "FLOATS_PER_ESTIMATE",
    "PAPER_NOISE_LEVELS",
    "Accuracy",
    "Alignment",
    "AlignmentError",
    "CentralizedResult",
    "DgsAgent",
    "DgsMessage",
    "DgsSettings",
    "DistributedResult",
    "Edge",
    "G2oError",
    "G2oInformationError",
    "G2oKeyError",
    "G2oQuaternionError",
    "GncResult",
    "GraphError",
    "LocalProblem",
    "MessageError",
    "PcmResult",
    "PcmSettings",
    "Pose",
    "PoseGraph",
    "RobotFolder",
    "Scenario",
    "ScenarioSettings",
    "SlamError",
    "SlamSettings",
    "SolveSummary",
    "StageSummary",
    "StepReport",
    "TraceEntry",
    "TwoStageResult",
    "accuracy",
    "are_star",
    "ate_star",
    "generate_scenario",
    "gnc",
    "is_landmark_key",
    "landmark_key",
    "main",
    "make_agents",
    "order_robots",
    "pcm",
    "pose_key",
    "ransac_rigid",
    "read_g2o",
    "read_robot_folder",
    "rigid_transform",
    "robot_of_key",
    "run_dgs",
    "solve_centralized",
    "solve_distributed",
    "solve_folder",
    "solve_two_stage",
    "stage_converged",
    "symbol_key",
    "write_g2o",
]
