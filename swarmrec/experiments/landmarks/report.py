"""The landmark simulation's figures and report (the WNBC paper's Figs. 3-5).

* :func:`recognition_rates`: the fraction of robots deciding their own landmark after
  ``k`` incorporated messages, per weight law (Fig. 3). A robot counts at ``k`` only if
  it incorporated at least ``k`` messages, so an incomplete round lowers the count
  ``n[k]`` rather than the rate.
* :func:`confusion_matrix`: true landmark x decided landmark after ``k`` messages (Fig. 5).
* :func:`plot_configuration`: a street, its facades in their landmarks' colours and the
  robots as triangles pointing along their yaw, filled with the colour of what they
  decided (Fig. 4).
* :func:`write_landmark_report`: ``report.md``, ``results.json`` and the PNGs.

Everything here works on the records of :mod:`.simulation` and has no I/O beyond the
files it writes. The summary is a typed record (:class:`LandmarksSummary`); ``results.json``
is its dictionary.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only: never needs a display

import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
from matplotlib.patches import Polygon

from swarmrec.experiments.landmarks.simulation import RobotRound, SimulationResult, reference_flood
from swarmrec.fusion.street import Street, SwarmConfiguration, default_street
from swarmrec.fusion.wnbc import N_LANDMARKS

__all__ = [
    "PAPER_FIG3",
    "LandmarksSummary",
    "confusion_matrix",
    "landmark_colours",
    "plot_configuration",
    "plot_confusion",
    "plot_recognition_rates",
    "recognition_rates",
    "write_landmark_report",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

#: What the paper's text states of its Fig. 3 (10 robots, 118 configurations); the curves
#: themselves are not published as numbers, so only these statements are compared.
PAPER_FIG3 = {
    "single robot": "68 %",
    "paper, λ = 0": "rises, then falls as far clusters' messages arrive (low at ten messages)",
    "paper, λ = 1": "about 90 % up to seven messages, then down to 30 % at ten",
    "paper, λ = 2": "stable, about 80 %",
    "paper, λ = 100": "constant at the single robot's rate",
}


def recognition_rates(
    rounds: Sequence[RobotRound], law: str, max_messages: int
) -> tuple[FloatArray, IntArray]:
    """``(rate[k], n[k])`` for ``k = 0 .. max_messages``: of the robots of ``law``'s rounds
    that incorporated at least ``k`` messages, the fraction whose decision after ``k`` was
    their true landmark (NaN where ``n[k]`` is 0)."""
    correct = np.zeros(max_messages + 1)
    count = np.zeros(max_messages + 1, np.int64)
    for r in rounds:
        if r.law != law:
            continue
        for k, decision in enumerate(r.decisions[: max_messages + 1]):
            count[k] += 1
            correct[k] += decision == r.truth
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(count > 0, correct / np.maximum(count, 1), np.nan)
    return rate, count


def confusion_matrix(rounds: Sequence[RobotRound], law: str, k: int | None = None) -> IntArray:
    """Counts ``[true landmark, decided landmark]`` after ``k`` messages (None: after all
    the robot incorporated)."""
    m = np.zeros((N_LANDMARKS, N_LANDMARKS), np.int64)
    for r in rounds:
        if r.law != law:
            continue
        if k is None:
            m[r.truth, r.decisions[-1]] += 1
        elif k < len(r.decisions):
            m[r.truth, r.decisions[k]] += 1
    return m


def landmark_colours(n: int = N_LANDMARKS) -> list[tuple[float, float, float]]:
    """A distinct colour per landmark: tab20's dark shades for the north side (0-9), its
    light shades for the south side, so facades side by side never share a hue pair."""
    cmap = plt.get_cmap("tab20")
    picks = ([*range(0, 20, 2), *range(1, 20, 2)] * (n // 20 + 1))[:n]
    return [tuple(float(c) for c in cmap(i)[:3]) for i in picks]  # type: ignore[misc]


def _wilson(p: float, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a proportion (honest error bars on 1180 robots)."""
    if n == 0 or math.isnan(p):
        return (math.nan, math.nan)
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (centre - half, centre + half)


def plot_recognition_rates(
    curves: dict[str, tuple[FloatArray, IntArray]], path: Path, title: str, target: float | None = 0.9
) -> None:
    """Fig. 3: correct recognition rate against incorporated messages, one line per law,
    with 95 % intervals."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, (rate, count) in curves.items():
        k = np.arange(len(rate))
        lo, hi = zip(*(_wilson(float(p), int(n)) for p, n in zip(rate, count, strict=True)), strict=True)
        line = ax.plot(k, 100 * rate, marker="o", ms=3, label=label)[0]
        ax.fill_between(k, 100 * np.array(lo), 100 * np.array(hi), color=line.get_color(), alpha=0.15)
    if target is not None:
        ax.axhline(100 * target, color="grey", lw=0.8, ls="--", label=f"{100 * target:.0f} % target")
    ax.set_xlabel("incorporated messages")
    ax.set_ylabel("correct recognition (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_confusion(matrix: IntArray, path: Path, title: str) -> None:
    """Fig. 5: the confusion matrix as a heat map, each true landmark's row normalised."""
    rows = matrix.sum(axis=1, keepdims=True)
    share = np.divide(matrix, rows, out=np.zeros(matrix.shape), where=rows > 0)
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    img = ax.imshow(100 * share, cmap="viridis", vmin=0, vmax=100)
    ticks = np.arange(matrix.shape[0])
    ax.set_xticks(ticks, [str(t) for t in ticks], fontsize=7)
    ax.set_yticks(ticks, [str(t) for t in ticks], fontsize=7)
    ax.set_xlabel("decided landmark")
    ax.set_ylabel("true landmark")
    ax.set_title(title, fontsize=10)
    fig.colorbar(img, ax=ax, fraction=0.046, label="% of the true landmark's robots")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _triangle(x: float, y: float, yaw: float, size: float) -> FloatArray:
    tip = (x + size * math.cos(yaw), y + size * math.sin(yaw))
    left = (x + 0.6 * size * math.cos(yaw + 2.5), y + 0.6 * size * math.sin(yaw + 2.5))
    right = (x + 0.6 * size * math.cos(yaw - 2.5), y + 0.6 * size * math.sin(yaw - 2.5))
    return np.array([tip, left, right])


def plot_configuration(
    ax: Any,
    config: SwarmConfiguration,
    decisions: Sequence[int],
    street: Street | None = None,
    title: str = "",
) -> None:
    """Fig. 4 on ``ax``: facades as coloured segments, radio links as grey lines, robots
    as triangles along their yaw filled with the colour of their decision; a robot whose
    decision is wrong gets a red edge. Zoomed on the robots and what they look at."""
    st = street or default_street()
    colours = landmark_colours(len(st.facades))
    xs = config.positions[:, 0]
    seen = {int(lm) for lm in config.landmarks} | {int(d) for d in decisions}
    x_lo = min([float(xs.min())] + [st.facade(lm).x0 for lm in seen]) - 2.0
    x_hi = max([float(xs.max())] + [st.facade(lm).x1 for lm in seen]) + 2.0
    for f in st.facades:
        y = st.facade_y(f.side)
        ax.plot([f.x0, f.x1], [y, y], color=colours[f.landmark], lw=6, solid_capstyle="butt")
        if x_lo <= f.centre <= x_hi:
            ax.text(f.centre, y + 0.9 * f.side, str(f.landmark), ha="center", va="center", fontsize=7)
    n = config.n_robots
    for i in range(n):
        for j in range(i + 1, n):
            if config.adjacency[i, j]:
                ax.plot(
                    *zip(config.positions[i], config.positions[j], strict=True), color="0.8", lw=0.6, zorder=1
                )
    for i in range(n):
        x, y = config.positions[i]
        right = int(decisions[i]) == int(config.landmarks[i])
        ax.add_patch(
            Polygon(
                _triangle(float(x), float(y), float(config.yaws[i]), 0.9),
                closed=True,
                facecolor=colours[int(decisions[i])],
                edgecolor="black" if right else "red",
                lw=0.8 if right else 2.0,
                zorder=3,
            )
        )
    ax.set_xlim(x_lo, x_hi)
    ax.set_ylim(-st.width / 2 - 2.0, st.width / 2 + 2.0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title, fontsize=9)


def _pick_examples(result: SimulationResult, law: str, count: int = 2) -> list[int]:
    """Configurations for Fig. 4: line formations with three clusters when there are such
    (the paper's examples), else any; the most-clusters ones first, deterministic."""

    def score(c: SwarmConfiguration) -> tuple[int, int, int]:
        return (int("line" in c.formations), len(c.cluster_landmarks) == 3, -c.index)

    ranked = sorted(result.configurations, key=score, reverse=True)
    decided = {(r.configuration, r.robot) for r in result.rounds if r.law == law}
    picks = [c.index for c in ranked if all((c.index, i) in decided for i in range(c.n_robots))]
    return picks[:count]


@dataclass
class RunInfo:
    configurations: int
    robots: int
    seed: int
    views: str
    radio_range_m: float
    laws: list[str]
    model: str


@dataclass
class LawRecognition:
    label: str
    #: Correct recognition after k = 0 .. n-1 incorporated messages (None: no robot got that far).
    rate: list[float | None]
    #: Robots counted at each k.
    robots: list[int]


@dataclass
class RoundBytes:
    rounds: int
    classifier_output_bytes_per_round: float
    classifier_output_messages_per_round: float
    bytes_per_message: float
    bytes_per_robot_per_round: float
    between_robots_by_message: dict[str, float]
    note: str = (
        "protobuf payload bytes the fusion services sent each other (scope 'swarm'), "
        "from their swarmrec_message_bytes_sent_total; a round is one configuration under one law"
    )


@dataclass
class Checks:
    robot_rounds: int
    expected_robot_rounds: int
    complete: int
    all_heard: int
    rejected_messages: int
    core_checked: int
    core_max_difference: float | None
    hops_equal_to_graph_distance: int
    hops_total: int


@dataclass
class LandmarksSummary:
    """Everything a simulation reports; ``results.json`` holds :meth:`to_dict`."""

    settings: RunInfo
    recognition: dict[str, LawRecognition]
    figure_law: str
    confusion_after_all: list[list[int]]
    fig4_configurations: list[int]
    bytes: RoundBytes
    checks: Checks
    failures: dict[str, int]
    errors: list[str]
    timings_s: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def complete(self) -> bool:
        """Every robot of every round recorded."""
        return self.checks.robot_rounds == self.checks.expected_robot_rounds


def _bytes(result: SimulationResult, n_rounds: int) -> RoundBytes:
    m = result.metrics
    by_type = m.by_label("swarmrec_message_bytes_sent_total", "message", scope="swarm")
    msgs = m.by_label("swarmrec_messages_sent_total", "message", scope="swarm")
    flood_bytes = by_type.get("ClassifierOutput", 0.0)
    flood_msgs = msgs.get("ClassifierOutput", 0.0)
    return RoundBytes(
        rounds=n_rounds,
        classifier_output_bytes_per_round=flood_bytes / n_rounds if n_rounds else 0.0,
        classifier_output_messages_per_round=flood_msgs / n_rounds if n_rounds else 0.0,
        bytes_per_message=flood_bytes / flood_msgs if flood_msgs else 0.0,
        bytes_per_robot_per_round=flood_bytes / n_rounds / result.settings.robots if n_rounds else 0.0,
        between_robots_by_message=dict(sorted(by_type.items())),
    )


def write_landmark_report(result: SimulationResult, figure_law: str | None = None) -> LandmarksSummary:
    """Write ``report.md``, ``results.json``, ``fig3_recognition.png``, ``fig4_configurations.png``
    and ``fig5_confusion.png`` into the run folder; returns the summary written to JSON.

    ``figure_law`` is the law of Figs. 4 and 5 (the paper's lambda 2 when it was run)."""
    s = result.settings
    out = s.out
    out.mkdir(parents=True, exist_ok=True)
    laws = {law.key: law for law in s.laws}
    if figure_law is None:
        figure_law = "paper:2" if "paper:2" in laws else s.laws[0].key
    max_k = s.robots - 1
    curves = {laws[key].label: recognition_rates(result.rounds, key, max_k) for key in laws}
    title = f"{s.configurations} configurations x {s.robots} robots, {s.views} views, over zenoh"
    plot_recognition_rates(curves, out / "fig3_recognition.png", title)
    matrix = confusion_matrix(result.rounds, figure_law, k=None)
    plot_confusion(
        matrix, out / "fig5_confusion.png", f"{laws[figure_law].label}, after all messages ({s.views} views)"
    )
    examples = _pick_examples(result, figure_law)
    fig, axes = plt.subplots(len(examples) or 1, 1, figsize=(9, 3.6 * max(1, len(examples))), squeeze=False)
    by_config = {c.index: c for c in result.configurations}
    for ax, index in zip(axes[:, 0], examples, strict=False):
        decisions = [0] * s.robots
        for r in result.rounds:
            if r.law == figure_law and r.configuration == index:
                decisions[r.robot] = r.decisions[-1]
        c = by_config[index]
        right = sum(d == t for d, t in zip(decisions, c.landmarks.tolist(), strict=True))
        plot_configuration(
            ax,
            c,
            decisions,
            title=f"configuration {index} ({', '.join(c.formations)}): {right}/{s.robots} right, "
            f"{laws[figure_law].label}",
        )
    fig.tight_layout()
    fig.savefig(out / "fig4_configurations.png", dpi=130)
    plt.close(fig)

    n_rounds = len(result.configurations) * len(s.laws)
    checked = [r.core_difference for r in result.rounds if r.core_difference is not None]
    hops_exact, hops_total = _hop_distances(result)
    summary = LandmarksSummary(
        settings=RunInfo(
            configurations=s.configurations,
            robots=s.robots,
            seed=s.seed,
            views=s.views,
            radio_range_m=s.radio_range,
            laws=list(laws),
            model=s.model or "models/landmarks/landmark_cnn.onnx",
        ),
        recognition={
            key: LawRecognition(
                label=laws[key].label,
                rate=[None if math.isnan(v) else round(float(v), 4) for v in rate],
                robots=count.tolist(),
            )
            for key, (rate, count) in zip(laws, curves.values(), strict=True)
        },
        figure_law=figure_law,
        confusion_after_all=matrix.tolist(),
        fig4_configurations=examples,
        bytes=_bytes(result, n_rounds),
        checks=Checks(
            robot_rounds=len(result.rounds),
            expected_robot_rounds=n_rounds * s.robots,
            complete=sum(r.complete for r in result.rounds),
            all_heard=sum(r.incorporated == s.robots - 1 for r in result.rounds),
            rejected_messages=sum(r.rejected for r in result.rounds),
            core_checked=len(checked),
            core_max_difference=max(checked) if checked else None,
            hops_equal_to_graph_distance=hops_exact,
            hops_total=hops_total,
        ),
        failures=result.failures,
        errors=result.errors[:50],
        timings_s={k: round(v, 2) for k, v in result.timings.items()},
    )
    (out / "results.json").write_text(json.dumps(summary.to_dict(), indent=2) + "\n", encoding="utf-8")
    (out / "report.md").write_text(_markdown(summary, curves), encoding="utf-8")
    return summary


def _hop_distances(result: SimulationResult) -> tuple[int, int]:
    """How many incorporated messages came with a hop count equal to the graph distance
    (a first copy may arrive by a longer path: zenoh does not deliver in BFS order). The
    distance is the hop count of the core's synchronous flooding, breadth-first by
    construction."""
    distance: dict[tuple[int, int, int], int] = {}
    for c in result.configurations:
        for robot, heard in enumerate(reference_flood(c).heard):
            distance.update({(c.index, robot, h.origin): h.hops for h in heard})
    exact = total = 0
    for r in result.rounds:
        for origin, hops, _yaw, _w in r.history:
            total += 1
            exact += hops == distance[(r.configuration, r.robot, origin)]
    return exact, total


def _markdown(summary: LandmarksSummary, curves: dict[str, tuple[FloatArray, IntArray]]) -> str:
    st = summary.settings
    checks = summary.checks
    b = summary.bytes
    k_max = st.robots - 1
    head = "| law | " + " | ".join(str(k) for k in range(k_max + 1)) + " |"
    rule = "|---|" + "---|" * (k_max + 1)
    rows = [
        f"| {label} | " + " | ".join("-" if math.isnan(v) else f"{100 * v:.1f}" for v in rate) + " |"
        for label, (rate, _n) in curves.items()
    ]
    lines = [
        "# Cooperative landmark recognition",
        "",
        f"{st.configurations} street configurations x {st.robots} robots, {st.views} views, "
        f"radio range {st.radio_range_m:g} m, seed {st.seed}; every robot a detector (classifier "
        "mode) and a fusion service, real processes over one zenoh router.",
        "",
        "## Correct recognition (%) after k incorporated messages (Fig. 3)",
        "",
        head,
        rule,
        *rows,
        "",
        "![Fig. 3](fig3_recognition.png)",
        "",
        "The paper's text on its Fig. 3 (not published as numbers): "
        + "; ".join(f"{k}: {v}" for k, v in PAPER_FIG3.items())
        + ".",
        "",
        f"## Confusion after all messages, {summary.figure_law} (Fig. 5)",
        "",
        "![Fig. 5](fig5_confusion.png)",
        "",
        "## Two configurations (Fig. 4)",
        "",
        "Robots are filled with the colour of the landmark they decided after all messages; a red "
        "edge marks a wrong decision; grey lines are radio links.",
        "",
        "![Fig. 4](fig4_configurations.png)",
        "",
        "## Bytes",
        "",
        f"- ClassifierOutput between robots: {b.classifier_output_bytes_per_round:.0f} B per round "
        f"({b.classifier_output_messages_per_round:.0f} messages of {b.bytes_per_message:.1f} B), "
        f"{b.bytes_per_robot_per_round:.0f} B per robot per round.",
        "",
        "## Checks",
        "",
        f"- robot-rounds recorded: {checks.robot_rounds} of {checks.expected_robot_rounds}; "
        f"complete (every copy delivered): {checks.complete}; heard every robot: {checks.all_heard}",
        f"- posteriors recomputed by the core from the same vectors in the same order: "
        f"{checks.core_checked}, largest difference {checks.core_max_difference}",
        f"- messages rejected by the fusion services: {checks.rejected_messages}",
        f"- hop counts equal to the graph distance: {checks.hops_equal_to_graph_distance} of "
        f"{checks.hops_total} (the rest came first by a longer path)",
        f"- failed classify calls: {summary.failures or 'none'}",
        "",
        "Timings (s): " + ", ".join(f"{k} {v}" for k, v in summary.timings_s.items()),
        "",
    ]
    return "\n".join(lines)
