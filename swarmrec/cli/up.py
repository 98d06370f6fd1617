"""``swarmrec up`` and ``swarmrec down``: a local swarm kept up until told to stop.

``up`` starts the places swarm as local processes (the built-in synthetic world by
default), prints and writes where it is (``OUT/swarm.json``: router, gateway, PKI, swarm
name) and keeps it until Ctrl-C or ``swarmrec down OUT``. Meanwhile ``swarmrec members``,
``query``, ``loop-closures`` and ``explain`` find it from the folder (``--run OUT``,
``runs/up`` by default), and ``swarmrec run --attach OUT`` replays through it."""

from __future__ import annotations

import argparse
import faulthandler
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from swarmrec.cli.clients import DEFAULT_SWARM_DIR
from swarmrec.cli.common import (
    Subparsers,
    add_dataset_flags,
    add_index_flags,
    add_local_swarm_flags,
    local_settings,
    swarm_places_settings,
)
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.local_up import (
    SWARM_FILE,
    keeper_alive,
    read_local_file,
    stop_kept,
    write_local_file,
)
from swarmrec.errors import ConfigError
from swarmrec.experiments.places.keep import local_up
from swarmrec.services.settings import IndexSettings

__all__ = ["add", "down", "up"]

#: How often the keeping process looks at its services.
WATCH_S = 1.0


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "up",
        help="start a local swarm and keep it up until Ctrl-C or `swarmrec down`",
        description=(
            "Start the places swarm as processes on this machine (a router, a gRPC gateway, and on "
            "each robot a detector, descriptor, index shard and verifier), wait until every service "
            "serves, then print and write where it is (OUT/swarm.json: router, gateway, PKI, swarm "
            "name) and keep it up. Client commands find it with --run OUT (runs/up by default); "
            "`swarmrec run --attach OUT` replays the dataset through it. Ctrl-C, SIGTERM or "
            "`swarmrec down OUT` stops it."
        ),
    )
    add_dataset_flags(p)
    p.add_argument("--robots", type=int, default=10, help="robots in the swarm (default 10)")
    p.add_argument("--swarm", default="local", help="swarm name (default local)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds a service waits for a peer")
    p.add_argument(
        "--out",
        type=Path,
        default=DEFAULT_SWARM_DIR,
        help=f"the swarm's folder: swarm.json, data, logs, PKI (default {DEFAULT_SWARM_DIR})",
    )
    p.add_argument(
        "--free",
        action="store_true",
        help="for free replay (run --attach --pace fast or a rate), not lock-step",
    )
    add_local_swarm_flags(p)
    p.add_argument(
        "--wire-positions",
        choices=("mm", "exact"),
        default="mm",
        help="object positions on the wire: mm (default) or exact doubles",
    )
    add_index_flags(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=up)

    d = sub.add_parser("down", help="stop the local swarm `swarmrec up` keeps")
    d.add_argument(
        "folder",
        type=Path,
        nargs="?",
        default=DEFAULT_SWARM_DIR,
        help=f"the swarm's folder (default {DEFAULT_SWARM_DIR})",
    )
    d.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for it to stop (default 60)")
    d.set_defaults(handler=down)


class _Stop(Exception):
    """SIGTERM (or a second Ctrl-C): stop the swarm."""


def _refuse_running(out: Path) -> None:
    path = out / SWARM_FILE
    if not path.is_file():
        return
    try:
        info = read_local_file(out)
    except ConfigError:
        raise ConfigError(
            f"{path} belongs to another swarm (compose or Kubernetes): choose another --out"
        ) from None
    if keeper_alive(info.pid):
        raise ConfigError(
            f"swarm {info.swarm!r} already runs from {out} (process {info.pid}): "
            f"use it, or stop it first (swarmrec down {out})"
        )


def up(args: argparse.Namespace) -> int:
    out = args.out.resolve()
    _refuse_running(out)
    # SIGUSR1 prints where every thread of this process is (stderr): a keeper that does not
    # stop can be asked what it waits on (`kill -USR1 <pid>`), as the tests do.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    settings = swarm_places_settings(
        args,
        out,
        wire_positions=args.wire_positions,
        data_plane=args.data_plane,
        index=IndexSettings(replicas=args.replicas, rebalance_target=args.rebalance_target),
        progress=not args.quiet,
    )

    def on_term(signum: int, frame: FrameType | None) -> None:
        raise _Stop()

    # SIGTERM stops the swarm as Ctrl-C does (the processes it started are stopped, never orphaned).
    signal.signal(signal.SIGTERM, on_term)
    t0 = time.perf_counter()
    try:
        deployment = LocalDeployment.for_run(out, local_settings(args))
        record = local_up(settings, deployment)
    except (KeyboardInterrupt, _Stop):
        print("stopped while starting; every process it had started is stopped", file=sys.stderr)
        return 130
    code = 0
    try:
        info = write_local_file(out, deployment, record)
        _print_up(info.swarm, args, deployment, out, time.perf_counter() - t0)
        code = _keep(deployment)
    except (KeyboardInterrupt, _Stop):
        pass
    finally:
        # A second Ctrl-C must not leave half the services running.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        print("stopping the swarm ...", flush=True)
        codes = deployment.stop()
        (out / SWARM_FILE).unlink(missing_ok=True)
        failed = {name: c for name, c in codes.items() if c != 0}
        if failed:
            print(f"swarm stopped; processes that did not exit cleanly: {failed} (logs in {out / 'logs'})")
        else:
            print(f"swarm stopped: {len(codes)} processes exited cleanly")
    return code


def _print_up(swarm: str, args: argparse.Namespace, deployment: LocalDeployment, out: Path, s: float) -> None:
    shown = _shown(out)
    processes = len(deployment.procs) + 1  # and the router
    security = "insecure (plaintext)" if deployment.security == "insecure" else "mutual TLS"
    print(
        f"swarm {swarm!r} of {args.robots} robots is up in {s:.1f} s "
        f"({processes} processes, {deployment.hosting} hosting, {security})"
    )
    print(f"  router   {deployment.endpoint}")
    print(f"  gateway  {deployment.gateway_address}")
    if deployment.live_view_url:
        print(f"  live     {deployment.live_view_url}   (open it in a browser)")
    if deployment.pki_dir is not None:
        print(f"  PKI      {deployment.pki_dir.resolve()}")
    print(f"  logs     {deployment.log_dir.resolve()}")
    print(f"  written to {shown / SWARM_FILE}; try:")
    run = "" if out == DEFAULT_SWARM_DIR.resolve() else f" --run {shown}"
    print(f"    swarmrec members{run}")
    print(f"    swarmrec run --attach {shown}")
    print(f"  Ctrl-C here, or swarmrec down {shown}, stops it.", flush=True)


def _shown(out: Path) -> Path:
    """``out`` as the user would type it: relative to here when it is below here."""
    try:
        return out.relative_to(Path.cwd())
    except ValueError:
        return out


def _keep(deployment: LocalDeployment) -> int:
    """Wait for a signal; say once when a service process exits. 1 if the router did."""
    reported: set[str] = set()
    while True:
        time.sleep(WATCH_S)
        router = deployment.router
        if router is not None and router.proc.poll() is not None:
            print(
                f"the router exited ({router.proc.returncode}): no service can be reached; "
                f"see {router.log_path}",
                file=sys.stderr,
            )
            return 1
        for sp in deployment.procs:
            if sp.proc.poll() is not None and sp.name not in reported:
                reported.add(sp.name)
                print(
                    f"warning: {sp.name} exited ({sp.proc.returncode}); see {deployment.log_dir}",
                    file=sys.stderr,
                    flush=True,
                )


def down(args: argparse.Namespace) -> int:
    folder: Path = args.folder
    path = folder / SWARM_FILE
    if not path.is_file():
        raise ConfigError(f"no swarm is kept in {folder} (no {SWARM_FILE} there)")
    try:
        read_local_file(folder)
    except ConfigError as e:
        hint = "a compose swarm: swarmrec compose down; Kubernetes: swarmrec k8s down"
        raise ConfigError(f"{e} ({hint})") from None
    print(stop_kept(folder, args.timeout))
    return 0
