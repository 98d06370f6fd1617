"""A router per robot, linked by radio range: the local mesh (docs/mesh.md).

In the mesh topology every robot runs its own zenoh router (the compiled one, with
mutual TLS and the swarm's access control, presenting ``r<robot>.router.<swarm>``);
the robot's services connect to it alone, and routers connect only to the robots
they hear. zenoh's routers route among themselves (link state, shortest path by hop
count), so a robot reaches a shard or a verifier it cannot hear through the robots
in between, with no change to any service.

Each link between two routers is a real one: a Toxiproxy proxy of its own
(``link-<a>-<b>``) in front of the higher robot's router, dialled by the lower
robot's. Cutting a link closes its proxy and every connection through it (a dial is
refused at once: the router behind it never sees one); healing it opens the proxy on
the same port (one below the OS's range for port 0, :func:`~swarmrec.deployments.links.reserved_port`,
so that nothing takes it meanwhile) and the dialling router connects within half a
second (``ROUTER_REDIAL_MAX_MS``). Rates and latencies are toxics on the proxy, each way.

In lock-step, :meth:`MeshLinks.apply` puts the links in a step's state and
:meth:`MeshLinks.wait_converged` returns only once every robot's router sees
exactly its component: through an operator session on each robot's own router it
lists the routers' liveliness tokens and compares them with the radio graph, so a
run is deterministic (checked, not slept).

What crossed each link is measured on the wire: every compiled router counts the
bytes it sent to and received from each neighbouring router
(``swarmrec_router_link_bytes_total{peer, direction}``, zenoh's own transport
counters, relayed traffic included).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from swarmrec.client import ZenohClient
from swarmrec.deployments.errors import DeploymentError
from swarmrec.deployments.links import LinkEmulator, LinkSpec, reserved_port
from swarmrec.deployments.metrics import Scrape
from swarmrec.deployments.radio import Pair, RadioGraph
from swarmrec.errors import CallError, ConfigError, WireError
from swarmrec.runtime import keys
from swarmrec.security.identity import parse_common_name
from swarmrec.services.registry import REGISTRY
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode

#: The compiled router's counter of bytes on its links to other routers, and its gauge of them.
LINK_BYTES = "swarmrec_router_link_bytes_total"
#: Its counter of payload bytes on those links by message type (zenoh's per-key counts).
KEY_BYTES = "swarmrec_router_key_bytes_total"
NEIGHBOURS = "swarmrec_router_neighbours"
GRAPH_LINKS = "swarmrec_router_graph_links"
#: The compiled router's page of its links, link state and zenoh id alone, beside its
#: metrics page (which also reads zenoh's counters: too costly to poll every 50 ms).
MESH_PAGE = "/mesh"
#: Its page with the bytes by message type too (zenoh's per-key counts), read while the
#: links do not change: read during link changes, a 10-robot mesh's routers stopped
#: answering their own admin space.
KEYS_PAGE = "/keys"
#: How often the routers are asked whether they follow a step's radio graph (each asking
#: reads every router's admin space once).
CONVERGE_POLL_S = 0.05
#: zenoh's routers recompute their routing trees this long after a change of the router
#: graph at most (zenoh 1.10's TREES_COMPUTATION_DELAY_MS, 100 ms, with a margin).
ZENOH_TREES_DELAY_S = 0.15
ZID = "swarmrec_router_zid"

__all__ = [
    "KEYS_PAGE",
    "KEY_BYTES",
    "LINK_BYTES",
    "MESH_PAGE",
    "MeshLinks",
    "MeshOperator",
    "MeshReport",
    "RouterView",
    "key_bytes",
    "link_bytes",
    "link_name",
    "mesh_report",
    "message_types",
    "router_views",
]


def link_name(pair: Pair) -> str:
    """The proxy of the link between robots ``pair`` (lower id first)."""
    return f"link-{pair[0]}-{pair[1]}"


@dataclass
class MeshLinks:
    """The links of a mesh: a proxy per pair that is ever linked, in the state of a step."""

    graph: RadioGraph
    emulator: LinkEmulator
    #: Proxy port of each pair (the lower robot's router dials it).
    ports: dict[Pair, int] = field(default_factory=dict)
    #: What each pair's proxy is now: its link spec, or None while cut.
    state: dict[Pair, LinkSpec | None] = field(default_factory=dict)

    def create(self) -> None:
        """A proxy per pair, cut and without an upstream yet (:meth:`connect_to` gives it
        one once the routers listen): nothing passes before :meth:`apply`."""
        taken: set[int] = set()
        for pair in self.graph.pairs():
            # Port 1 has no listener: a dial before the router is known is refused at once.
            port = self.emulator.add_proxy(link_name(pair), 1, reserved_port(taken))
            self.emulator.set_enabled(link_name(pair), False)
            self.ports[pair], self.state[pair] = port, None

    def dials(self, robot: int) -> list[int]:
        """The proxy ports ``robot``'s router dials: its links to higher robots."""
        return [port for (a, _b), port in sorted(self.ports.items()) if a == robot]

    def connect_to(self, router_ports: Sequence[int]) -> None:
        """Point each pair's proxy at the higher robot's router."""
        for a, b in self.ports:
            self.emulator.set_upstream(link_name((a, b)), router_ports[b])

    def apply(self, t: int) -> list[str]:
        """Put every link in step ``t``'s state; what changed, for the report."""
        want = self.graph.at(t)
        events = []
        for pair in sorted(self.ports):
            name, spec, now = link_name(pair), want.get(pair), self.state.get(pair)
            if spec == now:
                continue
            if spec is None:
                self.emulator.set_enabled(name, False)
                events.append(f"link {pair[0]}-{pair[1]} cut")
            else:
                self.emulator.set_toxics(name, spec)
                if now is None:
                    self.emulator.set_enabled(name, True)
                    events.append(f"link {pair[0]}-{pair[1]} up" + (f" {spec}" if spec.limited else ""))
                else:
                    events.append(f"link {pair[0]}-{pair[1]} {spec}")
            self.state[pair] = spec
        return events

    def wait_converged(
        self,
        t: int,
        operator: MeshOperator,
        views: Callable[[], dict[int, RouterView]],
        timeout_s: float = 60.0,
    ) -> float:
        """Wait until the routers follow step ``t``'s radio graph (checked, not slept): every
        router is linked to exactly its neighbours, its router graph (zenoh's link state) is
        exactly its component's links, and it sees exactly its component's routers and
        services (liveliness, listed through each robot's own router). ``views``: what each
        router's metrics say now. The seconds it took; DeploymentError naming what differs
        when it does not converge in ``timeout_s``."""
        start = time.monotonic()
        want = self.graph.component_of(t)
        links = self.graph.at(t)
        pending = set(range(self.graph.robots))
        wrong: dict[int, str] = {}
        while True:
            now = views()
            for r in sorted(pending):
                expected = frozenset(b if a == r else a for a, b in links if r in (a, b))
                view = now.get(r)
                if view is None:
                    wrong[r] = f"robot {r}'s router did not answer its scrape"
                    continue
                if view.neighbours != expected:
                    peers = "unknown routers" if view.neighbours is None else sorted(view.neighbours)
                    wrong[r] = f"robot {r}'s router is linked to {peers}, not robots {sorted(expected)}"
                    continue
                component_links = frozenset(p for p in links if p[0] in want[r])
                if view.graph != component_links:
                    shown = "unknown routers" if view.graph is None else sorted(view.graph)
                    wrong[r] = f"robot {r}'s router graph has links {shown}, not {sorted(component_links)}"
                    continue
                alive = operator.alive_at(r)
                seen = {robot for kind, robot in alive if kind == "router"}
                if seen != set(want[r]) or not operator.services_of(want[r]) <= alive:
                    wrong[r] = f"robot {r} sees routers {sorted(seen)}, not {sorted(want[r])}"
                    continue
                pending.discard(r)
                wrong.pop(r, None)
            if not pending:
                # The routers' own view is right; their routes follow it once zenoh has
                # recomputed its trees (debounced: ZENOH_TREES_DELAY_S). Then every robot asks
                # every router's info through its own router: the answers must be exactly its
                # component's, so each robot's queries reach what they should.
                time.sleep(ZENOH_TREES_DELAY_S)
                probing = set(range(self.graph.robots))
                while probing and time.monotonic() - start <= timeout_s:
                    for r in sorted(probing):
                        answered = operator.routers_answering(r)
                        if answered == set(want[r]):
                            probing.discard(r)
                        else:
                            wrong[r] = f"robot {r} reaches routers {sorted(answered)}, not {sorted(want[r])}"
                    if probing:
                        time.sleep(CONVERGE_POLL_S)
                if not probing:
                    return time.monotonic() - start
                pending = probing
            if time.monotonic() - start > timeout_s:
                raise DeploymentError(
                    f"the mesh did not converge to step {t}'s radio graph in {timeout_s:g} s: "
                    + "; ".join(wrong[r] for r in sorted(wrong))
                )
            time.sleep(CONVERGE_POLL_S)


@dataclass(frozen=True)
class RouterView:
    """What one robot's router says of the mesh now (its metrics, read at a scrape), in
    robots; None where it names a router whose robot is not known (its zenoh id unread)."""

    neighbours: frozenset[int] | None
    #: The links of its router graph (zenoh's link state).
    graph: frozenset[Pair] | None


def router_views(routers: Scrape) -> dict[int, RouterView]:
    """Each robot's router's :class:`RouterView`, from its ``swarmrec_router_neighbours``,
    ``swarmrec_router_zid`` and ``swarmrec_router_graph_links``."""
    zid_of: dict[str, int] = {}
    for (kind, robot), series in routers.samples.items():
        for (name, labels), v in series.items():
            if kind == "router" and name == ZID and v > 0:
                zid_of[dict(labels).get("zid", "")] = robot
    out: dict[int, RouterView] = {}
    for (kind, robot), series in routers.samples.items():
        if kind != "router":
            continue
        peers: set[int] | None = set()
        graph: set[Pair] | None = set()
        for (name, labels), v in series.items():
            d = dict(labels)
            if name == NEIGHBOURS and v > 0 and peers is not None:
                peer = zid_of.get(d.get("peer_zid", ""))
                peers = None if peer is None else peers | {peer}
            elif name == GRAPH_LINKS and v > 0 and graph is not None:
                a, b = zid_of.get(d.get("a", "")), zid_of.get(d.get("b", ""))
                graph = None if a is None or b is None else graph | {(min(a, b), max(a, b))}
        out[robot] = RouterView(
            None if peers is None else frozenset(peers), None if graph is None else frozenset(graph)
        )
    return out


class MeshOperator:
    """The operator of a mesh run: a session on every robot's own router, as a robot's
    own computer feeds its camera to its own services. A lock-step step reaches robot
    ``r``'s detector through robot ``r``'s router, so the replay itself crosses no link
    between robots; everything else a :class:`~swarmrec.client.ZenohClient` does goes
    through robot 0's router (``hub``)."""

    def __init__(
        self, clients: Sequence[ZenohClient], services: Callable[[int], set[tuple[str, int]]]
    ) -> None:
        if not clients:
            raise DeploymentError("a mesh operator needs a session per robot")
        self.clients = list(clients)
        self.hub = self.clients[0]
        self._services = services
        #: The robots whose own router accepted the operator's session.
        self.opened: list[int] = []

    def __enter__(self) -> MeshOperator:
        """Open a session on every robot's router; a router that cannot be reached (it died)
        leaves its robot to the hub, the first robot's router that can."""
        self.opened = []
        for r, c in enumerate(self.clients):
            try:
                c.__enter__()
            except CallError:
                continue  # its router is gone: the robot is reached through the hub, if at all
            self.opened.append(r)
        if not self.opened:
            raise DeploymentError("no robot's router of the mesh accepts the operator")
        self.hub = self.clients[self.opened[0]]
        return self

    def __exit__(self, *exc: object) -> None:
        for r in reversed(self.opened):
            self.clients[r].__exit__(None, None, None)
        self.opened = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.hub, name)

    def _through(self, robot: int) -> ZenohClient:
        """Robot ``robot``'s own session while it has its router; the hub's once that router
        is gone (a session without a router would wait out every call's timeout; through
        the hub a robot cut off answers nothing at once)."""
        own = self.clients[robot]
        return own if robot in self.opened and own.session.info.routers_zid() else self.hub

    def step(self, step: int, timeout_s: float, *, robot: int | None = None) -> list[Any]:
        """Step ``robot`` (default: every robot, each through its own router, at once)."""
        if robot is not None:
            return self._through(robot).step(step, timeout_s, robot=robot)
        out: list[list[Any]] = [[] for _ in self.clients]

        def one(r: int) -> None:
            out[r] = self._through(r).step(step, timeout_s, robot=r)

        threads = [
            threading.Thread(target=one, args=(r,), name=f"step-r{r}") for r in range(len(self.clients))
        ]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        return [item for items in out for item in items]

    def loop_closures(self, robot: int) -> Any:
        """Robot ``robot``'s loop closures, asked of its own router."""
        return self._through(robot).loop_closures(robot)

    def routers_answering(self, robot: int, timeout_s: float = 2.0) -> set[int]:
        """The robots whose routers answer robot ``robot``'s ask for their ``info``, sent
        through its own router: the routes from it, tried."""
        key = keys.endpoint(self.hub.swarm, "router", "*", "info")
        got: set[int] = set()
        replies = self._through(robot).session.get(
            key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s
        )
        for reply in replies:
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) >= 2 and parts[-2].isdigit():
                    got.add(int(parts[-2]))
        return got

    def descriptor_info(self, robot: int, timeout_s: float = 2.0) -> pb.MemberInfo | None:
        """What robot ``robot``'s descriptor says of itself (its pending stores), asked through
        its own router; None when it does not answer."""
        client = self._through(robot)
        key = keys.endpoint(client.swarm, "descriptor", robot, "info")
        for reply in client.session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                try:
                    return decode(reply.ok.payload.to_bytes(), pb.MemberInfo)
                except WireError:
                    return None
        return None

    def shard_states_at(self, robot: int) -> list[pb.ShardState]:
        """The index shards' states robot ``robot`` reaches (its component's), through its own router."""
        return list(self._through(robot).shard_states())

    def alive_at(self, robot: int) -> set[tuple[str, int]]:
        """(kind, robot) of every liveliness token robot ``robot``'s router knows now."""
        return self._through(robot).alive()

    def services_of(self, robots: frozenset[int]) -> set[tuple[str, int]]:
        return {s for r in robots for s in self._services(r)}


def link_bytes(routers: Scrape, swarm: str) -> dict[Pair, tuple[float, float]]:
    """Bytes on each link between two robots' routers, ``{(a, b): (a to b, b to a)}``
    (``a < b``), from the routers' :data:`LINK_BYTES` (each side counts what it sent;
    a router that did not answer the scrape counts nothing). ``routers`` is keyed by
    ("router", robot)."""
    out: dict[Pair, list[float]] = {}
    for (kind, robot), series in routers.samples.items():
        if kind != "router":
            continue
        for (name, labels), value in series.items():
            d = dict(labels)
            if name != LINK_BYTES or d.get("direction") != "sent":
                continue
            try:
                peer = parse_common_name(d.get("peer", ""))
            except ConfigError:
                continue  # an insecure mesh's routers are named by zenoh id: not attributable
            if peer.role != "router" or peer.swarm != swarm or peer.robot < 0 or peer.robot == robot:
                continue
            pair = (min(robot, peer.robot), max(robot, peer.robot))
            entry = out.setdefault(pair, [0.0, 0.0])
            entry[0 if robot < peer.robot else 1] += value
    return {p: (v[0], v[1]) for p, v in sorted(out.items())}


def message_types(swarm: str) -> dict[str, str]:
    """The message types robots send each other, ``{name: key expression}``: every endpoint
    some kind calls (``"index-shard query"``: its requests and their replies) and the
    events. A mesh's routers count the payload bytes of each on each link (``stats_keys``)."""
    calls = sorted({(c.kind, c.endpoint) for entry in REGISTRY.values() for c in entry.calls})
    out = {
        f"{kind} {endpoint}": keys.endpoint(swarm, kind, "*", f"{endpoint}/**") for kind, endpoint in calls
    }
    out["events"] = f"{keys.PREFIX}/{swarm}/events/**"
    return out


def key_bytes(routers: Scrape, swarm: str) -> dict[tuple[str, str], float]:
    """Payload bytes of each message type sent on the links between routers so far, summed
    over every link (so a relayed message counts once per link it crossed), by (message
    type, zenoh message: query, reply or put), from the routers' :data:`KEY_BYTES`."""
    names = {key: name for name, key in message_types(swarm).items()}
    out: dict[tuple[str, str], float] = {}
    for (kind, _robot), series in routers.samples.items():
        if kind != "router":
            continue
        for (name, labels), value in series.items():
            d = dict(labels)
            if name != KEY_BYTES or d.get("direction") != "sent" or d.get("key") not in names:
                continue
            try:
                peer = parse_common_name(d.get("peer", ""))
            except ConfigError:
                continue
            if peer.role != "router" or peer.swarm != swarm:
                continue
            entry = (names[d["key"]], d.get("message", ""))
            out[entry] = out.get(entry, 0.0) + value
    return dict(sorted(out.items()))


@dataclass
class MeshReport:
    """What a mesh run reports (``summary.json``'s ``mesh``): its radio graph over time,
    what each link carried, how long the routers took to follow each step's graph."""

    routers: int
    radio_range_m: float | None
    #: Runs of steps with the same components (:meth:`RadioGraph.timeline`).
    components: list[dict[str, object]]
    #: (step, what changed) for every link cut, restored or changed.
    events: list[tuple[int, str]]
    #: Bytes on each link during the replay, "a-b": {"a_to_b", "b_to_a"}, measured by the routers.
    link_bytes: dict[str, dict[str, float]]
    #: All the links' bytes over the replay's queries (relayed traffic counted on every link it crossed).
    link_bytes_per_query: float
    #: Seconds the routers took to follow each changed graph (checked, not slept).
    converge_s: list[float] = field(default_factory=list)
    #: The most links between two robots of one component, over the run.
    max_hops: int = 0
    #: Seconds the mesh's start took: its links, its routers (all at once), its first convergence.
    start_s: dict[str, float] = field(default_factory=dict)
    #: Seconds each link change then waited for the descriptors' pass over their pending stores.
    deliver_s: list[float] = field(default_factory=list)
    #: Payload bytes a query of each message type (and zenoh message: query, reply, put) on
    #: the links, summed over every link crossed: zenoh's per-key counts in the routers.
    type_bytes_per_query: dict[str, float] = field(default_factory=dict)
    #: While split: {"step", "version"} of the placement every part followed from that step.
    held_placements: list[dict[str, int]] = field(default_factory=list)
    #: While split: {"step", "versions"} where the parts did not all follow one placement (none
    #: expected: the coordinators change nothing while the team is split).
    split_disagreements: list[dict[str, object]] = field(default_factory=list)
    note: str = (
        "link bytes are zenoh's transport counters in each robot's router (what it sent to each "
        "neighbouring router: messages relayed for others included), read before and after the replay, "
        "less what crossed the links while they changed between two steps (closing links, the "
        "convergence checks)"
    )


def mesh_report(
    graph: RadioGraph,
    before: dict[Pair, tuple[float, float]],
    after: dict[Pair, tuple[float, float]],
    queries: int,
    events: Sequence[tuple[int, str]],
    converge_s: Sequence[float],
    start_s: dict[str, float] | None = None,
) -> MeshReport:
    """The report of a mesh run whose links carried ``after`` less ``before``."""
    delta = {
        f"{a}-{b}": {
            "a_to_b": after[(a, b)][0] - before.get((a, b), (0.0, 0.0))[0],
            "b_to_a": after[(a, b)][1] - before.get((a, b), (0.0, 0.0))[1],
        }
        for a, b in sorted(after)
    }
    total = sum(v["a_to_b"] + v["b_to_a"] for v in delta.values())
    hops = max((max(graph.hops_at(t).values(), default=0) for t in range(graph.steps)), default=0)
    return MeshReport(
        routers=graph.robots,
        radio_range_m=graph.range_m,
        components=graph.timeline(),
        events=list(events),
        link_bytes=delta,
        link_bytes_per_query=total / queries if queries else 0.0,
        converge_s=list(converge_s),
        max_hops=hops,
        start_s=dict(start_s or {}),
    )
