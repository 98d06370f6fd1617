"""The weighted naive Bayes classifier (WNBC) of Brent, Yuan and Stegagno, "Cooperative
Place Recognition in Robotic Swarms" (SAC '21), Sec. 3.4.

Robot ``A_i`` starts from its own classifier output ``p(z_i|O^i)`` (a uniform prior
``p(O^i)``, so the first posterior is that vector normalised) and folds in the
vectors ``p(z_h|O^h)`` of the other robots one at a time, in the order flooding
delivers them. Because ``A_h`` may look at another landmark, each message is mixed
in with the probability ``P(R_h^i)`` that both robots see the same landmark
(Eq. 12)::

    p(O^i | Z_i^k, z_h) = P(R) * alpha * p(O^i | Z_i^k) p(z_h | O^i)  +  (1 - P(R)) * p(O^i | Z_i^k)

``alpha`` normalises the naive Bayes product (Eq. 11). ``P(R)`` is the *mixture weight*
of the updated posterior, not an exponent on the likelihood: ``P(R) = 1`` is the plain
naive Bayes update, ``P(R) = 0`` leaves the posterior as it was. The paper's weight
(Eq. 14-16) multiplies a hop term and a yaw term::

    P(R) = (r + 1) ** -lambda * exp(-wrap(phi_i - phi_h) ** 2 / (2 * pi / 3))

where ``r`` is the communication distance (hops) and ``pi / 3`` the *variance* of the
zero-mean Gaussian of Eq. 15 (the paper says "pi/3 covariance"); the Gaussian is not
normalised, so equal yaws weigh 1 as the paper intends.

Numerics: the posterior is kept as logarithms, so hundreds of confident messages
never underflow; the naive Bayes product is normalised with log-sum-exp and the
mixture is taken with ``logaddexp``. Class scores are floored at
:data:`LIKELIHOOD_FLOOR` (after normalising to sum 1), because a classifier can
output an exact 0: with ``P(R) = 1`` one such zero would veto a class for the rest of
the round, and a message that is 0 wherever the posterior has mass would leave
``alpha`` undefined.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError, SwarmrecError

__all__ = [
    "LIKELIHOOD_FLOOR",
    "N_LANDMARKS",
    "WEIGHT_LAWS",
    "YAW_VARIANCE",
    "AgreementWeightLaw",
    "FusionState",
    "Incorporation",
    "LikelihoodError",
    "PaperWeightLaw",
    "WeightLaw",
    "hop_limit",
    "hop_weight",
    "make_weight_law",
    "normalise_likelihood",
    "wnbc_update",
    "wrap_angle",
    "yaw_weight",
]

FloatArray = npt.NDArray[np.float64]

#: Landmark classes of the paper's street (nineteen buildings).
N_LANDMARKS = 19
#: Smallest class score after normalisation: one message can lower a class by at most
#: a factor 1e6 (13.8 nats) instead of removing it for good; far above float underflow,
#: far below any score a 19-way classifier means.
LIKELIHOOD_FLOOR = 1e-6
#: Variance (rad^2) of the yaw Gaussian of Eq. 15: "zero mean and pi/3 covariance".
YAW_VARIANCE = math.pi / 3
#: Names accepted by :func:`make_weight_law`.
WEIGHT_LAWS: tuple[str, ...] = ("paper", "agreement")


class LikelihoodError(SwarmrecError, ValueError):
    """A class-score vector that cannot be a likelihood (wrong length, NaN, negative, all zero)."""


def wrap_angle(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi], so that yaws 350 and 10 degrees differ by 20, not 340."""
    return math.remainder(angle, 2 * math.pi)


def hop_weight(hops: int, lam: float) -> float:
    """Eq. 14: ``p(R | r) = (r + 1) ** -lambda``; robots further away on the graph are
    less likely to watch the same landmark. ``lam = 0`` gives 1 (the unweighted NBC)."""
    if hops < 0:
        raise ValueError(f"hops must be >= 0, got {hops}")
    return float((hops + 1.0) ** -lam)


def yaw_weight(yaw_difference: float, variance: float = YAW_VARIANCE) -> float:
    """Eq. 15: an unnormalised zero-mean Gaussian of the wrapped yaw difference; robots
    facing opposite ways (difference near pi) are unlikely to watch the same landmark."""
    d = wrap_angle(yaw_difference)
    return math.exp(-d * d / (2.0 * variance))


def hop_limit(lam: float, tolerance: float) -> int | None:
    """The ``r_max`` of Sec. 3.4: the largest hop count whose weight (Eq. 14) is still
    ``>= tolerance``. Messages further away weigh less than ``tolerance`` and need not be
    forwarded, which bounds traffic in large swarms. ``None`` when ``lam <= 0`` (no
    distance ever weighs less)."""
    if not 0.0 < tolerance < 1.0:
        raise ConfigError(f"tolerance must be in (0, 1), got {tolerance}")
    if lam <= 0:
        return None
    # (r + 1) ** -lam >= tol  <=>  r <= tol ** (-1 / lam) - 1; the small slack keeps exact
    # powers (tol = 2 ** -lam) on the inclusive side despite rounding.
    return max(0, math.floor(float(tolerance ** (-1.0 / lam)) * (1 + 1e-12)) - 1)


def normalise_likelihood(
    values: npt.ArrayLike, n_classes: int = N_LANDMARKS, floor: float = LIKELIHOOD_FLOOR
) -> FloatArray:
    """Class scores as a likelihood vector: divided by their sum (Sec. 3.2, "this grade is
    divided by the sum of the grades"), floored at ``floor`` and normalised again."""
    try:
        v = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise LikelihoodError(f"class scores are not numbers: {exc}") from None
    if not 0.0 < floor < 1.0 / n_classes:
        raise ConfigError(f"floor must be in (0, 1/{n_classes}), got {floor}")
    if v.shape[0] != n_classes:
        raise LikelihoodError(f"expected {n_classes} class scores, got {v.shape[0]}")
    if not np.all(np.isfinite(v)):
        raise LikelihoodError("class scores contain NaN or infinity")
    if np.any(v < 0):
        raise LikelihoodError("class scores contain a negative value")
    total = float(v.sum())
    if total <= 0:
        raise LikelihoodError("class scores are all zero")
    floored: FloatArray = np.maximum(v / total, floor)
    floored /= floored.sum()
    return floored


def _logsumexp(x: FloatArray) -> float:
    top = float(x.max())
    return top + math.log(float(np.exp(x - top).sum()))


def _check_weight(weight: float) -> None:
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight P(R) must be in [0, 1], got {weight}")


def _update_log(log_posterior: FloatArray, log_likelihood: FloatArray, weight: float) -> FloatArray:
    """Eq. 12 on logarithms (see the module docstring)."""
    product = log_posterior + log_likelihood
    naive = product - _logsumexp(product)  # alpha of Eq. 11
    if weight >= 1.0:
        return naive
    if weight <= 0.0:
        return log_posterior.copy()
    mixed = np.logaddexp(math.log(weight) + naive, math.log1p(-weight) + log_posterior)
    return mixed - _logsumexp(mixed)  # only rounding to remove: both terms sum to 1


def wnbc_update(
    posterior: npt.ArrayLike, likelihood: npt.ArrayLike, weight: float, floor: float = LIKELIHOOD_FLOOR
) -> FloatArray:
    """One step of Eq. 12: ``weight * alpha * posterior * likelihood + (1 - weight) * posterior``.

    ``posterior`` is ``p(O^i | Z_i^k)``, ``likelihood`` the received ``p(z_h | O^h)``
    (normalised and floored here), ``weight`` is ``P(R_h^i)`` (Eq. 13 gives the other
    term ``1 - weight``). Returns the new posterior, summing to 1.
    """
    _check_weight(weight)
    post = np.asarray(posterior, dtype=np.float64).reshape(-1)
    lik = normalise_likelihood(likelihood, post.shape[0], floor)
    if not (np.all(np.isfinite(post)) and np.all(post >= 0) and post.sum() > 0):
        raise LikelihoodError("posterior must be finite, non-negative and not all zero")
    with np.errstate(divide="ignore"):  # a zero posterior class stays at -inf, i.e. stays 0
        log_post = np.log(post / post.sum())
    return np.exp(_update_log(log_post, np.log(lik), weight))


class WeightLaw(Protocol):
    """How much a received message counts: the ``P(R_h^i)`` of Eq. 12, in [0, 1].

    A law sees the communication distance ``hops`` (``r_h^i``, at least 1), the yaw
    difference ``phi_i - phi_h`` (not wrapped), the message's normalised likelihood,
    the receiver's current posterior and how many messages it has already
    incorporated, so adaptive laws can use any of them.
    """

    @property
    def name(self) -> str: ...

    def weight(
        self,
        *,
        hops: int,
        yaw_difference: float,
        likelihood: FloatArray,
        posterior: FloatArray,
        incorporated: int,
    ) -> float: ...


@dataclass(frozen=True)
class PaperWeightLaw:
    """Eq. 16: ``P(R) = p(R | r) p(R | phi_i - phi_h)``, the hop term of Eq. 14 times the
    yaw Gaussian of Eq. 15; ignores the message's content."""

    #: lambda of Eq. 14; the paper ran 0 (unweighted), 1, 2 and 100 (single robot).
    lam: float = 2.0
    #: Variance of the yaw Gaussian (rad^2).
    yaw_variance: float = YAW_VARIANCE

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lam) and self.lam >= 0):
            raise ConfigError(f"lambda must be finite and >= 0, got {self.lam}")
        if not (math.isfinite(self.yaw_variance) and self.yaw_variance > 0):
            raise ConfigError(f"yaw variance must be finite and > 0, got {self.yaw_variance}")

    @property
    def name(self) -> str:
        return "paper"

    def weight(
        self,
        *,
        hops: int,
        yaw_difference: float,
        likelihood: FloatArray,
        posterior: FloatArray,
        incorporated: int,
    ) -> float:
        return hop_weight(hops, self.lam) * yaw_weight(yaw_difference, self.yaw_variance)


@dataclass(frozen=True)
class AgreementWeightLaw:
    """An adaptive law (the paper's conclusion asks for one): the paper's ``P(R)`` taken
    as a *prior* and updated with the message itself.

    The derivation of Eq. 9 keeps ``p(R)`` fixed, but ``z_h`` is evidence about ``R``
    too: if ``A_h`` watches another landmark, its vector says nothing about ``O^i`` and
    is, from ``A_i``'s side, as likely under every class (a landmark drawn uniformly),
    so ``p(z_h | R = 0) ~ mean_l p(z_h | l)``; if it watches the same one,
    ``p(z_h | R = 1, Z_i^k) ~ sum_l p(O^i = l | Z_i^k) p(z_h | l)``. Bayes' rule gives::

        P(R | z_h) = w a / (w a + (1 - w) u),  a = <posterior, likelihood>,  u = mean(likelihood)

    With this weight Eq. 12 is the exact posterior of the mixture model "same landmark
    with probability w, else an unrelated one". A message that agrees with the current
    belief keeps (or gains) weight; one that contradicts a confident belief, typically
    from a robot of another cluster, loses weight, so the many far messages that arrive
    last barely move a belief that the near ones made confident, while a robot whose own
    view was ambiguous still listens. ``w = 1`` (lambda 0) stays 1 and ``w = 0`` stays 0.
    On the simulated street (``tests/unit/test_wnbc.py``) it keeps the recognition rate
    above 90 % after every number of messages, where the paper's lambda 0 and 1 collapse.
    """

    #: The prior weight; lambda 1 gives near neighbours a strong say.
    prior: PaperWeightLaw = field(default_factory=lambda: PaperWeightLaw(lam=1.0))

    @property
    def name(self) -> str:
        return "agreement"

    def weight(
        self,
        *,
        hops: int,
        yaw_difference: float,
        likelihood: FloatArray,
        posterior: FloatArray,
        incorporated: int,
    ) -> float:
        w = self.prior.weight(
            hops=hops,
            yaw_difference=yaw_difference,
            likelihood=likelihood,
            posterior=posterior,
            incorporated=incorporated,
        )
        if w <= 0.0 or w >= 1.0:
            return w
        agree = float(posterior @ likelihood)
        unrelated = float(likelihood.mean())
        return w * agree / (w * agree + (1.0 - w) * unrelated)


def make_weight_law(
    name: str = "paper", *, lam: float | None = None, yaw_variance: float = YAW_VARIANCE
) -> WeightLaw:
    """A named weight law: ``paper`` (Eq. 16, lambda 2 unless given) or ``agreement``
    (:class:`AgreementWeightLaw`, its prior's lambda 1 unless given)."""
    if name == "paper":
        return PaperWeightLaw(lam=2.0 if lam is None else lam, yaw_variance=yaw_variance)
    if name == "agreement":
        return AgreementWeightLaw(PaperWeightLaw(lam=1.0 if lam is None else lam, yaw_variance=yaw_variance))
    raise ConfigError(f"unknown weight law {name!r}; known: {', '.join(WEIGHT_LAWS)}")


@dataclass(frozen=True, eq=False)
class Incorporation:
    """One message folded into a :class:`FusionState` and the posterior it left."""

    origin: int
    hops: int
    yaw_difference: float
    weight: float
    posterior: FloatArray


class FusionState:
    """Robot ``A_i``'s WNBC for one recognition round.

    Starts from the robot's own classifier output (uniform prior), incorporates received
    messages one at a time (Eq. 12 with ``law``'s weight) and keeps the posterior after
    each, so a caller can read the decision after any number of incorporated messages
    (the x axis of the paper's Fig. 3). A message is *ignored*, and counted by reason,
    when its origin was already incorporated (or is this robot) or it travelled more than
    ``r_max`` hops. Make a new state for each round.
    """

    def __init__(
        self,
        own_likelihood: npt.ArrayLike,
        own_yaw: float,
        law: WeightLaw,
        *,
        own_id: int | None = None,
        r_max: int | None = None,
        floor: float = LIKELIHOOD_FLOOR,
    ) -> None:
        if r_max is not None and r_max < 0:
            raise ConfigError(f"r_max must be >= 0 or None, got {r_max}")
        n_classes = int(np.size(own_likelihood))
        if n_classes < 2:
            raise LikelihoodError(f"need at least 2 classes, got {n_classes}")
        own = normalise_likelihood(own_likelihood, n_classes, floor)
        if not math.isfinite(own_yaw):
            raise ValueError(f"own yaw must be finite, got {own_yaw}")
        self.own_yaw = own_yaw
        self.law = law
        self.r_max = r_max
        self.floor = floor
        self.n_classes = n_classes
        self._log_posterior = np.log(own)
        self._seen: set[int] = set() if own_id is None else {own_id}
        self._own_id = own_id
        self._history: list[Incorporation] = []
        #: Ignored messages by reason ("duplicate origin", "own message", "beyond r_max").
        self.ignored_reasons: Counter[str] = Counter()
        self._initial = own

    def incorporate(
        self, origin: int, likelihood: npt.ArrayLike, hops: int, yaw: float
    ) -> Incorporation | None:
        """Fold in ``A_origin``'s message received at communication distance ``hops``
        (``r_h^i >= 1``) with its yaw; ``None`` (and counted) when it is ignored."""
        if hops < 1:
            raise ValueError(f"a received message has travelled at least 1 hop, got {hops}")
        if not math.isfinite(yaw):
            raise ValueError(f"yaw must be finite, got {yaw}")
        if origin == self._own_id:
            self.ignored_reasons["own message"] += 1
            return None
        if origin in self._seen:
            self.ignored_reasons["duplicate origin"] += 1
            return None
        if self.r_max is not None and hops > self.r_max:
            self.ignored_reasons["beyond r_max"] += 1
            return None
        lik = normalise_likelihood(likelihood, self.n_classes, self.floor)
        yaw_difference = self.own_yaw - yaw
        weight = float(
            self.law.weight(
                hops=hops,
                yaw_difference=yaw_difference,
                likelihood=lik,
                posterior=self.posterior,
                incorporated=len(self._history),
            )
        )
        _check_weight(weight)
        self._log_posterior = _update_log(self._log_posterior, np.log(lik), weight)
        self._seen.add(origin)
        step = Incorporation(origin, hops, yaw_difference, weight, self.posterior)
        self._history.append(step)
        return step

    @property
    def posterior(self) -> FloatArray:
        """``p(O^i | Z_i^k)`` now (a copy)."""
        return np.exp(self._log_posterior)

    @property
    def log_posterior(self) -> FloatArray:
        """The natural logarithm of :attr:`posterior` (a copy); finite even where the posterior underflows."""
        return self._log_posterior.copy()

    @property
    def decision(self) -> int:
        """The Bayes classifier of Eq. 2: the most probable landmark now."""
        return int(np.argmax(self._log_posterior))

    @property
    def incorporated(self) -> int:
        return len(self._history)

    @property
    def ignored(self) -> int:
        return sum(self.ignored_reasons.values())

    @property
    def history(self) -> Sequence[Incorporation]:
        """Incorporated messages in order, each with the posterior after it."""
        return tuple(self._history)

    def posterior_after(self, k: int) -> FloatArray:
        """The posterior after ``k`` incorporated messages (0: the robot's own output)."""
        if not 0 <= k <= len(self._history):
            raise IndexError(f"{len(self._history)} messages incorporated, asked for {k}")
        return (self._initial if k == 0 else self._history[k - 1].posterior).copy()

    def decision_after(self, k: int) -> int:
        """The decision (Eq. 2) after ``k`` incorporated messages."""
        return int(np.argmax(self.posterior_after(k)))
