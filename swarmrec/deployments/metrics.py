"""The services' counters, read from their own ``/metrics`` endpoints or from a
Prometheus server, and summed the way reports need them.

This is the one parser of the Prometheus text format in the project: the
deployments, the reports and the tests all read counters through :class:`Scrape`.
"""

from __future__ import annotations

import json
import time
import urllib.parse
import urllib.request
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

__all__ = ["Scrape", "parse_metrics", "read_metrics", "scrape", "scrape_prometheus"]


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

    def minus(self, before: Scrape) -> Scrape:
        """These counters less ``before``'s: a long-running swarm's traffic since ``before``."""
        out = Scrape(failed=list(self.failed))
        for target, series in self.samples.items():
            old = before.samples.get(target, {})
            out.samples[target] = {k: v - old.get(k, 0.0) for k, v in series.items()}
        return out

    def of_kind(self, kind: str) -> Scrape:
        """The samples of the services of ``kind`` only."""
        return Scrape({t: series for t, series in self.samples.items() if t[0] == kind}, list(self.failed))

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


def read_metrics(url: str, timeout_s: float = 5.0) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """The samples of one ``/metrics`` URL (see :func:`parse_metrics`); OSError when unreachable."""
    with urllib.request.urlopen(url, timeout=timeout_s) as resp:
        return parse_metrics(resp.read().decode("utf-8"))


def scrape(targets: dict[tuple[str, int], str], timeout_s: float = 5.0, *, parallel: int = 1) -> Scrape:
    """GET every ``/metrics`` URL, ``parallel`` at a time; an unreachable one is listed in
    ``failed`` (in the targets' order either way)."""
    result = Scrape()

    def read(url: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float] | None:
        try:
            return read_metrics(url, timeout_s)
        except OSError:
            return None

    if parallel > 1:
        with ThreadPoolExecutor(max_workers=parallel) as pool:
            pages = list(pool.map(read, targets.values()))
    else:
        pages = [read(url) for url in targets.values()]
    for (service, robot), page in zip(targets, pages, strict=True):
        if page is None:
            result.failed.append(f"{service}-{robot}")
        else:
            result.samples[(service, robot)] = page
    return result


def _rfc3339(text: str) -> float:
    """Seconds since the epoch of Prometheus' RFC 3339 times (nanosecond fractions allowed)."""
    from datetime import datetime

    head, dot, frac = text.rstrip("Z").partition(".")
    # datetime reads at most microseconds; the zone is UTC (Z) in Prometheus' API.
    stamp = head + (dot + frac[:6] if dot else "") + "+00:00"
    return datetime.fromisoformat(stamp).timestamp()


def _get_json(url: str, timeout_s: float) -> Any:
    with urllib.request.urlopen(url, timeout=timeout_s) as resp:
        return json.loads(resp.read().decode("utf-8"))


def scrape_prometheus(
    base_url: str,
    job: str = "swarmrec",
    *,
    fresh_after: float,
    timeout_s: float = 60.0,
    down_grace_s: float = 10.0,
) -> Scrape:
    """The services' samples as a Prometheus server last scraped them.

    Waits until Prometheus has scraped every target that is up after
    ``fresh_after`` (seconds since the epoch), so the figures include all the
    traffic before that instant, then reads every series of ``job`` through
    ``/federate``. Targets are told apart by their ``service`` and ``robot``
    labels (the generated scrape configuration sets them); a target that is
    down is listed in ``failed``, as an unreachable endpoint is by :func:`scrape`.

    One scrape that timed out says little on a loaded machine (the swarm's scrape timeout
    is 1 s): a target that is down gets ``down_grace_s`` (a few scrapes) to answer again
    before it counts as failed.
    """
    deadline = time.monotonic() + timeout_s
    down_deadline = time.monotonic() + min(down_grace_s, timeout_s)
    while True:
        targets = [
            t
            for t in _get_json(f"{base_url}/api/v1/targets?state=active", 5.0)["data"]["activeTargets"]
            if t["labels"].get("job") == job
        ]
        up = [t for t in targets if t["health"] == "up"]
        all_up_fresh = all(_rfc3339(t["lastScrape"]) > fresh_after for t in up)
        if targets and all_up_fresh and (len(up) == len(targets) or time.monotonic() > down_deadline):
            break
        if time.monotonic() > deadline:
            raise TimeoutError(f"Prometheus at {base_url} has not scraped every target in {timeout_s:g} s")
        time.sleep(0.5)
    result = Scrape()
    result.failed = sorted(f"{t['labels']['service']}-{t['labels']['robot']}" for t in targets if t not in up)
    query = urllib.parse.urlencode({"match[]": f'{{job="{job}"}}'})
    with urllib.request.urlopen(f"{base_url}/federate?{query}", timeout=10.0) as resp:
        text = resp.read().decode("utf-8")
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            labels = dict(s.labels)
            service, robot = labels.pop("service", None), labels.pop("robot", None)
            if service is None or robot is None:
                continue
            for extra in ("job", "instance"):
                labels.pop(extra, None)
            series = result.samples.setdefault((service, int(robot)), {})
            series[(s.name, tuple(sorted(labels.items())))] = float(s.value)
    return result
