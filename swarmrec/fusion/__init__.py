"""Cooperative landmark recognition: classifier outputs -> flooding -> weighted naive Bayes fusion.

The pure core of Brent, Yuan and Stegagno, "Cooperative Place Recognition in Robotic
Swarms" (SAC '21): :mod:`~swarmrec.fusion.wnbc` fuses the class probabilities of the
robots of a swarm with the weighted naive Bayes classifier (Eq. 12-16);
:mod:`~swarmrec.fusion.flooding` spreads them over the communication graph
(Algorithm 1); :mod:`~swarmrec.fusion.street` builds the simulated street of 19
landmarks and the swarm configurations in it; :mod:`~swarmrec.fusion.facades` renders
what a robot's camera sees of a landmark. No I/O beyond writing a preview image.

>>> from swarmrec.fusion import FusionState, PaperWeightLaw
>>> state = FusionState([0.5, 0.3, 0.2], 0.0, PaperWeightLaw(lam=1.0))
>>> step = state.incorporate(origin=1, likelihood=[0.2, 0.5, 0.3], hops=1, yaw=0.0)
>>> round(step.weight, 3), state.decision
(0.5, 0)
"""

from swarmrec.fusion.facades import (
    FACADE_DESIGNS,
    IMAGE_SIZE,
    FacadeDesign,
    RenderSettings,
    View,
    render_dataset,
    render_view,
    sample_view,
    write_preview,
)
from swarmrec.fusion.flooding import (
    FloodingNode,
    FloodMessage,
    FloodResult,
    Heard,
    Outcome,
    Reception,
    Rejection,
    simulate_flooding,
)
from swarmrec.fusion.street import (
    FORMATIONS,
    Facade,
    Sighting,
    Street,
    StreetSettings,
    SwarmConfiguration,
    communication_graph,
    default_street,
    generate_configuration,
    generate_configurations,
    is_connected,
)
from swarmrec.fusion.wnbc import (
    LIKELIHOOD_FLOOR,
    N_LANDMARKS,
    WEIGHT_LAWS,
    YAW_VARIANCE,
    AgreementWeightLaw,
    FusionState,
    Incorporation,
    LikelihoodError,
    PaperWeightLaw,
    WeightLaw,
    hop_limit,
    hop_weight,
    make_weight_law,
    normalise_likelihood,
    wnbc_update,
    wrap_angle,
    yaw_weight,
)

__all__ = [
    "FACADE_DESIGNS",
    "FORMATIONS",
    "IMAGE_SIZE",
    "LIKELIHOOD_FLOOR",
    "N_LANDMARKS",
    "WEIGHT_LAWS",
    "YAW_VARIANCE",
    "AgreementWeightLaw",
    "Facade",
    "FacadeDesign",
    "FloodMessage",
    "FloodResult",
    "FloodingNode",
    "FusionState",
    "Heard",
    "Incorporation",
    "LikelihoodError",
    "Outcome",
    "PaperWeightLaw",
    "Reception",
    "Rejection",
    "RenderSettings",
    "Sighting",
    "Street",
    "StreetSettings",
    "SwarmConfiguration",
    "View",
    "WeightLaw",
    "communication_graph",
    "default_street",
    "generate_configuration",
    "generate_configurations",
    "hop_limit",
    "hop_weight",
    "is_connected",
    "make_weight_law",
    "normalise_likelihood",
    "render_dataset",
    "render_view",
    "sample_view",
    "simulate_flooding",
    "wnbc_update",
    "wrap_angle",
    "write_preview",
    "yaw_weight",
]
