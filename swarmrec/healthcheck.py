"""Container health check: exit 0 when the service in this container serves.

``python -m swarmrec.healthcheck [--port P]`` reads the service's own
Prometheus endpoint on loopback (port: ``--port``, else ``SWARMREC_METRICS_PORT``,
else 9464) and succeeds when ``swarmrec_service_ready`` is 1: the service has
declared its liveliness token and not begun to stop. A process that hangs, or
a service still loading its stored data, fails the check.

Only the standard library is imported: Docker runs this every few seconds in
every container.
"""

from __future__ import annotations

import argparse
import os
import sys
import urllib.request

READY_METRIC = "swarmrec_service_ready"
DEFAULT_PORT = 9464
_SUMMARY = "Exit 0 when the service in this container serves."


def is_ready(metrics_text: str) -> bool:
    """Whether a ``/metrics`` page says the service is ready."""
    for line in metrics_text.splitlines():
        name, _, value = line.partition(" ")
        if name == READY_METRIC:
            try:
                return float(value) == 1.0
            except ValueError:
                return False
    return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m swarmrec.healthcheck", description=_SUMMARY)
    port = int(os.environ.get("SWARMREC_METRICS_PORT", DEFAULT_PORT))
    parser.add_argument("--port", type=int, default=port, help=f"metrics port (default {port})")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds (default 2)")
    args = parser.parse_args(argv)
    url = f"http://127.0.0.1:{args.port}/metrics"
    try:
        with urllib.request.urlopen(url, timeout=args.timeout) as resp:
            text = resp.read().decode("utf-8", errors="replace")
    except OSError as e:
        print(f"unhealthy: {url}: {e}", file=sys.stderr)
        return 1
    if not is_ready(text):
        print(f"unhealthy: {READY_METRIC} is not 1 at {url}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
