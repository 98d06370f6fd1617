"""Read the services' Prometheus endpoints and sum what the report needs."""

from __future__ import annotations

import urllib.request
from collections import defaultdict
from dataclasses import dataclass, field

from prometheus_client.parser import text_string_to_metric_families

__all__ = ["Scrape", "parse_metrics", "scrape"]


@dataclass
class Scrape:
    """Samples of many services: ``samples[(service, robot)][(name, labels)] = value``."""

    samples: dict[tuple[str, int], dict[tuple[str, tuple[tuple[str, str], ...]], float]] = field(
        default_factory=dict
    )
    failed: list[str] = field(default_factory=list)

    def total(self, name: str, **match: str) -> float:
        """Sum of ``name`` over every service whose labels include ``match``."""
        out = 0.0
        for series in self.samples.values():
            for (n, labels), v in series.items():
                if n == name and all(dict(labels).get(k) == val for k, val in match.items()):
                    out += v
        return out

    def by_label(self, name: str, label: str, **match: str) -> dict[str, float]:
        out: dict[str, float] = defaultdict(float)
        for series in self.samples.values():
            for (n, labels), v in series.items():
                d = dict(labels)
                if n == name and label in d and all(d.get(k) == val for k, val in match.items()):
                    out[d[label]] += v
        return dict(out)

    def per_service(self, name: str, kind: str) -> dict[int, float]:
        """``name`` summed per robot, over the services of ``kind``."""
        out: dict[int, float] = defaultdict(float)
        for (service, robot), series in self.samples.items():
            if service != kind:
                continue
            for (n, _labels), v in series.items():
                if n == name:
                    out[robot] += v
        return dict(out)


def parse_metrics(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """The samples of one ``/metrics`` page (Prometheus text format):
    ``{(sample name, sorted (label, value) pairs): value}``."""
    series: dict[tuple[str, tuple[tuple[str, str], ...]], float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            series[(s.name, tuple(sorted(s.labels.items())))] = float(s.value)
    return series


def scrape(targets: dict[tuple[str, int], str], timeout_s: float = 5.0) -> Scrape:
    """GET every ``/metrics`` URL; an unreachable one is listed in ``failed``."""
    result = Scrape()
    for (service, robot), url in targets.items():
        try:
            with urllib.request.urlopen(url, timeout=timeout_s) as resp:
                text = resp.read().decode("utf-8")
        except OSError:
            result.failed.append(f"{service}-{robot}")
            continue
        result.samples[(service, robot)] = parse_metrics(text)
    return result
