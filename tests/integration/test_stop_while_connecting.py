"""A service still waiting for its router stops on SIGTERM, Python or compiled.

A client waits for its router as long as it takes (``connect/timeout_ms`` -1), and zenoh's
open does not return until then. Both runtimes used to sit in it deaf to SIGTERM: a pod
whose router was down ran out its grace period and was killed, and a local swarm waited
10 s per process before its SIGKILL. Now the session is opened on a thread of its own
(``runner.open_session``, the compiled host's ``open_session``) and the service exits at
once, saying so. Real processes: ``swarmrec serve verifier`` pointed at a port nobody
listens on.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest


@pytest.mark.parametrize("data_plane", ["python", "compiled"])
def test_a_service_waiting_for_its_router_stops_on_sigterm(data_plane: str, refused_port: int) -> None:
    cmd = [
        sys.executable, "-m", "swarmrec", "serve", "verifier", "--security", "insecure",
        "--connect", f"tcp/127.0.0.1:{refused_port}", "--robot", "0", "--n-robots", "2",
        "--data-plane", data_plane, "--metrics-port", "-1",
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(3.0)  # long enough to be inside zenoh's open, retrying
        assert proc.poll() is None, proc.communicate()
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=5.0)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert took < 2.0
    assert not [line for line in out.splitlines() if '"ready"' in line]  # it never said it was ready
    said = [json.loads(line) for line in err.splitlines() if line.startswith("{")]
    assert any(m.get("msg") == "stopped before reaching the swarm" for m in said), err
