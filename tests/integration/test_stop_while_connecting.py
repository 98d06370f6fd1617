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
from pathlib import Path

import pytest

from tests.integration.support import wait_until


@pytest.mark.parametrize("data_plane", ["python", "compiled"])
def test_a_service_waiting_for_its_router_stops_on_sigterm(
    data_plane: str, refused_port: int, tmp_path: Path
) -> None:
    cmd = [
        sys.executable, "-m", "swarmrec", "serve", "verifier", "--security", "insecure",
        "--connect", f"tcp/127.0.0.1:{refused_port}", "--robot", "0", "--n-robots", "2",
        "--data-plane", data_plane, "--metrics-port", "-1",
    ]  # fmt: skip
    out_path, err_path = tmp_path / "out", tmp_path / "err"
    with out_path.open("w") as out_file, err_path.open("w") as err_file:
        proc = subprocess.Popen(cmd, stdout=out_file, stderr=err_file, text=True)
    try:
        # It says where it connects once SIGTERM is its own (a busy machine takes seconds to
        # get there); then it is in zenoh's open, retrying the port that refuses it.
        wait_until(
            lambda: "connecting to the swarm" in err_path.read_text() or proc.poll() is not None,
            60,
            "the service's line before it connects",
        )
        time.sleep(1.0)
        assert proc.poll() is None, err_path.read_text()
        proc.send_signal(signal.SIGTERM)
        # Deaf to SIGTERM it would never exit (zenoh's open retries for ever): the bound is
        # generous for a busy machine, the test is that it exits by itself, cleanly.
        proc.wait(timeout=10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out, err = out_path.read_text(), err_path.read_text()
    assert proc.returncode == 0, err
    assert not [line for line in out.splitlines() if '"ready"' in line]  # it never said it was ready
    said = [json.loads(line) for line in err.splitlines() if line.startswith("{")]
    connecting = [m for m in said if m.get("msg") == "connecting to the swarm"]
    assert connecting and connecting[0]["connect"] == [f"tcp/127.0.0.1:{refused_port}"], connecting
    assert any(m.get("msg") == "stopped before reaching the swarm" for m in said), err
