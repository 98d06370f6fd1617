"""``swarmrec up`` / ``down``: a local swarm kept up, found by clients from its folder.

As a user types it, every command a separate process: ``swarmrec up`` starts a
3-robot swarm (robots hosting, the compiled data plane, mutual TLS) and keeps it;
``members`` and ``loop-closures`` find it with ``--run DIR`` (and with no flag at
all from ``runs/up``); ``run --attach DIR`` replays the synthetic office through it
and its pair scores equal the offline evaluation; a second ``up`` on the folder is
refused; ``down`` stops it (every process exits 0, the file is gone, the router's
port is closed) and the clients then say so in one line.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

ROBOTS, FRAMES = 3, 120

#: What the module's swarm fixture gives: the folder it runs in, `swarmrec up`, what it printed.
Kept = tuple[Path, subprocess.Popen[str], list[str]]


def swarmrec(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "swarmrec", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        cwd=cwd,
    )


def _ctrl_c_as_at_a_terminal() -> None:
    # A shell without job control starts a background command with SIGINT ignored, and
    # every child inherits that (`(make test &)` did, and `swarmrec up` never saw the
    # test's Ctrl-C: its stacks showed it still keeping the swarm). A user types Ctrl-C at
    # a terminal, where SIGINT is not ignored: so is the keeper here.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_up(cwd: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "swarmrec", "up", "--quiet", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=cwd,
        preexec_fn=_ctrl_c_as_at_a_terminal,
    )


def wait_up(proc: subprocess.Popen[str], timeout_s: float = 120.0) -> list[str]:
    """The lines ``swarmrec up`` printed until it said how to stop it."""
    assert proc.stdout is not None
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"swarmrec up exited ({proc.wait()}):\n" + "".join(lines))
        lines.append(line)
        if "stops it" in line:
            return lines
    raise AssertionError("swarmrec up did not come up:\n" + "".join(lines))


@pytest.fixture(scope="module")
def kept(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Kept]:
    cwd = tmp_path_factory.mktemp("up")
    proc = start_up(cwd, "--robots", str(ROBOTS), "--frames", str(FRAMES), "--hosting", f"robots:{ROBOTS}")
    try:
        lines = wait_up(proc)
        yield cwd, proc, lines
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)


def test_up_says_where_the_swarm_is_and_writes_it(kept: Kept) -> None:
    cwd, proc, lines = kept
    info = json.loads((cwd / "runs/up/swarm.json").read_text())
    text = "".join(lines)

    assert info["deployment"] == "local" and info["pid"] == proc.pid
    assert info["robots"] == ROBOTS and info["swarm"] == "local" and info["security"] == "mtls"
    assert info["router_endpoint"].startswith("tls/127.0.0.1:") and info["router_endpoint"] in text
    assert info["gateway_address"].startswith("grpc://127.0.0.1:") and info["gateway_address"] in text
    assert Path(info["pki_dir"], "ca.pem").is_file() and info["pki_dir"] in text
    assert "swarmrec down runs/up" in text


def test_clients_find_it_by_folder_and_by_default(kept: Kept) -> None:
    cwd, _, _ = kept

    by_folder = swarmrec("members", "--run", "runs/up", "--json", cwd=cwd)
    by_default = swarmrec("members", "--json", cwd=cwd)

    assert by_folder.returncode == 0, by_folder.stderr
    assert by_default.returncode == 0, by_default.stderr
    for done in (by_folder, by_default):
        members = {(m["kind"], m["robot"]) for m in json.loads(done.stdout)}
        for kind in ("detector", "descriptor", "index-shard", "verifier"):
            assert {(kind, r) for r in range(ROBOTS)} <= members, members
        assert ("gateway", 0) in members and ("router", 0) in members


def test_a_second_up_on_the_folder_is_refused(kept: Kept) -> None:
    cwd, proc, _ = kept

    done = swarmrec("up", "--robots", "2", "--quiet", cwd=cwd, timeout=60)

    assert done.returncode == 2
    assert f"already runs from {cwd / 'runs/up'} (process {proc.pid})" in done.stderr
    assert json.loads((cwd / "runs/up/swarm.json").read_text())["pid"] == proc.pid


def test_run_attach_replays_through_it_as_offline_and_clients_see_the_closures(
    kept: Kept,
) -> None:
    cwd, _, _ = kept

    done = swarmrec("run", "--attach", "runs/up", "--no-plots", "--quiet", cwd=cwd, timeout=300)

    assert done.returncode == 0, done.stdout + done.stderr
    assert "pair scores vs offline decentralized evaluation: identical" in done.stdout
    assert "kept up by swarmrec up" in done.stdout
    with (cwd / "runs/up/report/loop_closures.csv").open() as f:
        rows = list(csv.DictReader(f))
    for robot in range(ROBOTS):
        live = swarmrec("loop-closures", str(robot), "--run", "runs/up", "--json", cwd=cwd)
        assert live.returncode == 0, live.stderr
        in_report = [r for r in rows if int(r["query_robot"]) == robot]
        assert len(json.loads(live.stdout)) == len(in_report)
    assert rows, "the office's first frames close loops"
    again = swarmrec("run", "--attach", "runs/up", "--no-plots", "--quiet", cwd=cwd, timeout=120)
    assert again.returncode == 2 and "already holds data" in again.stderr and "swarmrec down" in again.stderr


def test_down_stops_every_process_and_clients_then_say_so(
    kept: Kept,
) -> None:
    cwd, proc, _ = kept
    info = json.loads((cwd / "runs/up/swarm.json").read_text())
    port = int(info["router_endpoint"].rsplit(":", 1)[1])

    done = swarmrec("down", cwd=cwd)

    assert done.returncode == 0, done.stderr
    assert f"swarm 'local' stopped ({ROBOTS} robots, process {proc.pid})" in done.stdout
    rest, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert "processes exited cleanly" in rest
    assert not (cwd / "runs/up/swarm.json").exists()
    with pytest.raises(OSError), socket.create_connection(("127.0.0.1", port), timeout=2):
        pass
    after = swarmrec("members", "--run", "runs/up", cwd=cwd)
    assert after.returncode == 2
    assert after.stderr.strip().count("\n") == 0 and "no swarm is kept there" in after.stderr
    again = swarmrec("down", cwd=cwd)
    assert again.returncode == 2 and "no swarm is kept in runs/up" in again.stderr


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # gone meanwhile
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def test_sigint_while_kept_stops_it_cleanly(tmp_path: Path) -> None:
    proc = start_up(tmp_path, "--robots", "2", "--frames", "40", "--hosting", "robots:2", "--out", "s")
    wait_up(proc)

    proc.send_signal(signal.SIGINT)

    try:
        rest, _ = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        # Say where it hangs (its threads' stacks, faulthandler on SIGUSR1), then end it.
        proc.send_signal(signal.SIGUSR1)
        time.sleep(2.0)
        for child in _children(proc.pid):  # its swarm, which it did not stop
            os.kill(child, signal.SIGKILL)
        proc.kill()
        stacks, _ = proc.communicate()
        raise AssertionError(f"swarmrec up did not stop 60 s after Ctrl-C; it was at:\n{stacks}") from None
    assert proc.returncode == 0
    assert "processes exited cleanly" in rest
    assert not (tmp_path / "s/swarm.json").exists()


def test_down_never_signals_a_process_that_reused_a_dead_swarms_pid(tmp_path: Path) -> None:
    # A stale file whose pid now belongs to some other program: down must not touch it.
    other = subprocess.Popen(["sleep", "60"])
    try:
        folder = tmp_path / "stale"
        folder.mkdir()
        stale = {
            "deployment": "local", "swarm": "local", "robots": 1, "workload": "places", "kinds": [],
            "router_endpoint": "tls/127.0.0.1:1", "prometheus_url": "", "pid": other.pid,
        }  # fmt: skip
        (folder / "swarm.json").write_text(json.dumps(stale))

        done = swarmrec("down", "stale", cwd=tmp_path)
        members = swarmrec("members", "--run", "stale", cwd=tmp_path)

        assert done.returncode == 0 and "stale swarm.json removed" in done.stdout
        assert other.poll() is None
        assert not (folder / "swarm.json").exists()
        assert members.returncode == 2
    finally:
        os.kill(other.pid, signal.SIGKILL)
        other.wait()
