"""The live view: a web page of the running swarm, served by the gateway.

The gateway (:mod:`swarmrec.services.gateway`) already sees the whole swarm as a
read-only client. The live view puts that in a browser, with nothing to build and
nothing fetched from outside: one HTML page (:mod:`.live_view_page`, plain
JavaScript), ``/api/state`` (JSON, read when the page asks, at most every
:data:`STATE_CACHE_S`) and ``/api/events`` (server-sent events as they happen).

What it shows, for every method the swarm runs: the members and their health
(liveliness: a member that left is shown as gone) and loop closures as they arrive;
for constellations, each index shard's label groups and stored frames, the load on
each shard (partial queries, from the shards' metrics), the placement's version
history and the loop-closure funnel of the queries seen (queried, candidates
returned, pairs verified, closures); for full-image descriptors, the load on each
cluster owner, the cluster table's version history and the place queries' funnel
(answered, matched, verified, closures); for SLAM, each robot's solve (state, stage,
iteration) and its trajectory, objects and separators (:mod:`.live_view_slam`); the
bytes between robots by message type (from every member's metrics), and fusion
decisions.

It listens on ``web_host`` (loopback by default) and every request must carry the
token printed with its address (``?token=``, as Jupyter does), since the page
shows what the swarm's mutual TLS otherwise guards. It never changes anything in
the swarm, and its cost is bounded: at most ``web_max_streams`` event streams (more
are answered 503), each with a bounded queue (a reader too slow loses its oldest
events, counted in the stream), state reads cached, metrics read with a short
timeout on a few threads.
"""

from __future__ import annotations

import contextlib
import json
import queue
import secrets
import threading
import time
import urllib.request
from collections import deque
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, TypeVar
from urllib.parse import parse_qs, urlsplit

import zenoh
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]
from prometheus_client.parser import text_string_to_metric_families

from swarmrec.client import ZenohClient
from swarmrec.runtime import keys
from swarmrec.services.live_view_page import PAGE
from swarmrec.services.live_view_slam import separator_keys, slam_robot_view
from swarmrec.wire import messages as pb

__all__ = ["MAX_CONNECTIONS", "STATE_CACHE_S", "LiveView", "event_is_publishers"]

M = TypeVar("M", bound=Message)
E = TypeVar("E", pb.LoopClosure, pb.QueryReport, pb.FusionUpdate, pb.PlaceReport)

#: The page's state is read from the swarm at most this often, however many pages ask.
STATE_CACHE_S = 1.0
#: Events kept for a page opened late, and queued for each stream.
RECENT_EVENTS = 200
STREAM_QUEUE = 1000
#: A stream sends a comment this often when nothing happens, so a dead reader is noticed.
KEEPALIVE_S = 10.0
#: How long the metrics of one member may take to read.
SCRAPE_TIMEOUT_S = 1.0
#: Connections served at once (each has a thread); more are closed unanswered.
MAX_CONNECTIONS = 32
#: A connection that sends nothing (or reads nothing) this long is closed.
IDLE_TIMEOUT_S = 30.0
#: SLAM robots whose solve and estimate the page shows (each costs three requests a poll).
MAX_SLAM_ROBOTS = 26


def _closure_json(c: pb.LoopClosure) -> dict[str, Any]:
    return {
        "query_robot": c.query_robot_id,
        "query_frame": c.query_frame_index,
        "match_robot": c.match_robot_id,
        "match_frame": c.match_frame_index,
        "score": round(c.score, 4),
        "n_matched": c.n_matched,
        "unix_time_ns": c.unix_time_ns,
    }


class LiveView:
    """The HTTP server of the page, fed by zenoh subscribers of the gateway's session."""

    def __init__(
        self,
        session: zenoh.Session,
        swarm: str,
        client: ZenohClient,
        *,
        host: str,
        port: int,
        max_streams: int,
        log: Any,
    ) -> None:
        self.session, self.swarm, self.client, self.log = session, swarm, client, log
        self.token = secrets.token_urlsafe(18)
        self.max_streams = max_streams
        self.lock = threading.Lock()
        self.streams: list[_Stream] = []
        self.closures: deque[dict[str, Any]] = deque(maxlen=RECENT_EVENTS)
        self.fusion: deque[dict[str, Any]] = deque(maxlen=50)
        self.fusion_total = 0
        self.funnel = {"queries": 0, "queried": 0, "candidates": 0, "verified_pairs": 0, "closures": 0}
        self.place_funnel = {"queries": 0, "answered": 0, "matched": 0, "verified": 0, "closures": 0}
        # The separators each SLAM robot sent, by (robot, solve): read once a solve.
        self.separators: dict[tuple[int, int], dict[int, list[int]]] = {}
        self.tables: list[tuple[float, int]] = []  # the cluster table's versions, as seen
        self.left: dict[str, float] = {}  # members whose liveliness token went away, and when
        self.placements: list[tuple[float, int]] = []
        self.started = time.time()
        self._state: tuple[float, dict[str, Any]] | None = None
        self._state_lock = threading.Lock()
        self._scraper = ThreadPoolExecutor(4, thread_name_prefix="live-view-scrape")
        self._subscribers = [
            session.declare_subscriber(keys.event(swarm, "loop_closure", "*"), self._on_closure),
            session.declare_subscriber(keys.event(swarm, "query", "*"), self._on_report),
            session.declare_subscriber(keys.event(swarm, "place_query", "*"), self._on_place_report),
            session.declare_subscriber(keys.event(swarm, "fusion", "*"), self._on_fusion),
            session.liveliness().declare_subscriber(keys.alive_all(swarm), self._on_alive),
        ]
        view = self

        class Handler(_Handler):
            live = view

        self.server = _Server((host, port), Handler)
        self.port = int(self.server.server_address[1])
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        self.url = f"http://{shown}:{self.port}/?token={self.token}"
        self.thread = threading.Thread(target=self.server.serve_forever, name="live-view", daemon=True)
        self.thread.start()

    def close(self) -> None:
        for sub in self._subscribers:
            with contextlib.suppress(Exception):
                sub.undeclare()  # type: ignore[no-untyped-call]  # zenoh's stub leaves it untyped
        self.server.shutdown()
        self.server.server_close()
        with self.lock:
            for q in self.streams:
                q.offer(("end", {}))
        self._scraper.shutdown(wait=False, cancel_futures=True)

    # --- events from the swarm (zenoh's callbacks: quick, never blocking) ---------------

    def _publish(self, kind: str, data: dict[str, Any]) -> None:
        with self.lock:
            for q in self.streams:
                q.offer((kind, data))

    def _on_closure(self, sample: zenoh.Sample) -> None:
        c = _decode(pb.LoopClosure, sample)
        if c is None:
            return
        data = _closure_json(c)
        with self.lock:
            self.closures.append(data)
            self.funnel["closures"] += 1
        self._publish("closure", data)

    def _on_report(self, sample: zenoh.Sample) -> None:
        r = _decode(pb.QueryReport, sample)
        if r is None:
            return
        with self.lock:
            f = self.funnel
            f["queries"] += 1
            f["queried"] += int(r.queried)
            f["candidates"] += r.n_candidates
            f["verified_pairs"] += len(r.matches)
            counts = dict(f)
        self._publish(
            "report",
            {"robot": r.robot_id, "frame": r.frame_index, "duration_us": r.duration_us, "funnel": counts},
        )

    def _on_place_report(self, sample: zenoh.Sample) -> None:
        r = _decode(pb.PlaceReport, sample)
        if r is None:
            return
        with self.lock:
            f = self.place_funnel
            f["queries"] += 1
            f["answered"] += int(r.answered)
            f["matched"] += int(r.answered and r.match.found)
            f["verified"] += int(r.verified)
            f["closures"] += int(r.loop_closure)
            counts = dict(f)
        self._publish(
            "place_report",
            {"robot": r.robot_id, "frame": r.frame_index, "duration_us": r.duration_us, "funnel": counts},
        )

    def _on_fusion(self, sample: zenoh.Sample) -> None:
        u = _decode(pb.FusionUpdate, sample)
        if u is None:
            return
        data = {"robot": u.robot_id, "round": u.round_id, "decision": u.decision, "heard_all": u.heard_all}
        with self.lock:
            self.fusion.append(data)
            self.fusion_total += 1
        self._publish("fusion", data)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse_alive(str(sample.key_expr))
        if parsed is None:
            return
        name = f"{parsed[0]}-{parsed[1]}"
        alive = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            if alive:
                self.left.pop(name, None)
            else:
                self.left[name] = time.time()
        self._publish("member", {"name": name, "alive": alive})

    # --- the state a page reads -------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """The swarm now (cached for STATE_CACHE_S)."""
        with self._state_lock:
            if self._state is not None and time.monotonic() - self._state[0] < STATE_CACHE_S:
                return self._state[1]
            state = self._read_state()
            self._state = (time.monotonic(), state)
            return state

    def _read_state(self) -> dict[str, Any]:
        members, error = [], ""
        try:
            members = self.client.members()
        except Exception as e:  # the page shows why, and keeps polling
            error = f"members: {e}"
        placement: dict[str, Any] = {}
        try:
            ix = self.client.index_state(members=members)
            version = ix.placement.version if ix.placement is not None else -1
            with self.lock:
                if version >= 0 and (not self.placements or self.placements[-1][1] != version):
                    self.placements.append((time.time(), version))
                    del self.placements[:-50]
                history = list(self.placements)
            placement = {"version": version, "settled": ix.settled, "pending": ix.pending, "history": history}
        except Exception as e:
            error = error or f"index: {e}"
        # Each member's /metrics once (several members of one process have paths of their own).
        urls = sorted({m.metrics_url for m in members if m.metrics_url})
        scraped = dict(zip(urls, self._scraper.map(_scrape, urls), strict=True))
        # A shard's (an owner's) load is read from a URL that serves that member alone.
        alone_at: dict[tuple[str, str], list[int]] = {}
        for m in members:
            if m.kind in _LOAD_METRIC:
                alone_at.setdefault((m.kind, m.metrics_url), []).append(m.robot)
        by_message: dict[str, float] = {}
        load: dict[str, dict[int, float]] = {kind: {} for kind in _LOAD_METRIC}
        for url, series in scraped.items():
            for name, labels, value in series:
                # scope "swarm": what crossed between robots (the report's bytes are these too).
                if name == "swarmrec_message_bytes_sent_total" and labels.get("scope") == "swarm":
                    by_message[labels["message"]] = by_message.get(labels["message"], 0.0) + value
                for kind, metric in _LOAD_METRIC.items():
                    robots = alone_at.get((kind, url), [])
                    if name == metric and len(robots) == 1:
                        load[kind][robots[0]] = load[kind].get(robots[0], 0.0) + value
        table = self._cluster_table(sorted(m.robot for m in members if m.kind == "place-owner"))
        slam = self._slam_state(sorted(m.robot for m in members if m.kind == "slam"))
        with self.lock:
            if table >= 0 and (not self.tables or self.tables[-1][1] != table):
                self.tables.append((time.time(), table))
                del self.tables[:-50]
            tables = list(self.tables)
            closures = list(self.closures)[-50:]
            funnel = dict(self.funnel)
            place_funnel = dict(self.place_funnel)
            fusion = list(self.fusion)[-10:]
            fusion_total = self.fusion_total
            left = dict(self.left)
        return {
            "swarm": self.swarm,
            "time": time.time(),
            "up_s": time.time() - self.started,
            "error": error,
            "members": [
                {
                    "kind": m.kind,
                    "robot": m.robot,
                    "stored": m.stored_items,
                    "pending": m.pending_items,
                    "groups": [f"{lo}-{hi}" for lo, hi in m.label_ranges],
                    "version": m.version,
                }
                for m in members
            ],
            "left": sorted(left),
            "placement": placement,
            "shard_load": {str(r): v for r, v in sorted(load["index-shard"].items())},
            "owner_load": {str(r): v for r, v in sorted(load["place-owner"].items())},
            "cluster_table": {"version": table, "history": tables},
            "place_funnel": place_funnel,
            "slam": slam,
            "bytes_by_message": dict(sorted(by_message.items(), key=lambda kv: -kv[1])),
            "closures": closures,
            "closures_total": funnel["closures"],
            "funnel": funnel,
            "fusion": fusion,
            "fusion_total": fusion_total,
        }

    def _ask(self, kind: str, robot: int, endpoint: str, request: Message, reply: type[M]) -> M:
        """One read-only request to ``kind`` of ``robot``, waited for at most SCRAPE_TIMEOUT_S."""
        key = keys.endpoint(self.swarm, kind, robot, endpoint)
        return self.client.call(key, request, reply, target_robot=robot, timeout_s=SCRAPE_TIMEOUT_S)

    def _cluster_table(self, owners: list[int]) -> int:
        """The cluster table's version, as the first place owner that answers has it (-1: none)."""
        for robot in owners[:3]:
            try:
                reply = self._ask(
                    "place-owner", robot, "assignment", pb.AssignmentRequest(), pb.AssignmentReply
                )
            except Exception:
                continue
            return int(reply.version)
        return -1

    def _slam_state(self, robots: list[int]) -> list[dict[str, Any]]:
        """Each SLAM robot's solve and drawing (:mod:`.live_view_slam`), read in parallel."""
        return list(self._scraper.map(self._slam_robot, robots[:MAX_SLAM_ROBOTS]))

    def _slam_robot(self, robot: int) -> dict[str, Any]:
        try:
            status = self._ask("slam", robot, "status", pb.SlamStatusRequest(), pb.SlamStatus)
            estimate = self._ask("slam", robot, "estimate", pb.SlamEstimateRequest(), pb.SlamEstimate)
            with self.lock:
                shared = self.separators.get((robot, status.solve_id))
            if shared is None and status.order:
                # The first page holds a step to every neighbour once the team has stepped.
                page = self._ask("slam", robot, "sent", pb.SlamSentRequest(offset=0), pb.SlamSentPage)
                shared = separator_keys(page.steps)
                if shared or status.state in _SLAM_ENDED:
                    with self.lock:  # one solve a robot kept: the newest
                        for old in [k for k in self.separators if k[0] == robot]:
                            del self.separators[old]
                        self.separators[(robot, status.solve_id)] = shared
        except Exception as e:  # the page shows why, and keeps polling
            return slam_robot_view(None, None, {}, robot, error=str(e))
        return slam_robot_view(status, estimate, shared or {}, robot)

    # --- event streams ----------------------------------------------------------------

    def open_stream(self) -> _Stream | None:
        """A queue of events for one reader, or None when ``max_streams`` are open."""
        with self.lock:
            if len(self.streams) >= self.max_streams:
                return None
            q = _Stream()
            self.streams.append(q)
            return q

    def close_stream(self, q: _Stream) -> None:
        with self.lock:
            if q in self.streams:
                self.streams.remove(q)


#: The field of each streamed event that names the robot it is about.
_EVENT_ROBOT_FIELD = {
    "LoopClosure": "query_robot_id",
    "QueryReport": "robot_id",
    "FusionUpdate": "robot_id",
    "PlaceReport": "robot_id",
}
#: The load of a shard or a cluster owner: the robots' queries it answered.
_LOAD_METRIC = {
    "index-shard": "swarmrec_shard_partial_queries_total",
    "place-owner": "swarmrec_place_owner_queries_total",
}
#: States after which a SLAM robot sends nothing more in its solve.
_SLAM_ENDED = (pb.SlamState.SLAM_STATE_DONE, pb.SlamState.SLAM_STATE_ABORTED, pb.SlamState.SLAM_STATE_FAILED)


def event_is_publishers(msg: Any, key: str) -> bool:
    """Whether ``msg``, published on ``key``, is about the robot whose key it came on: the
    router lets a robot's services publish on their own robot's keys only, so a payload
    naming another robot is a forgery (issue 28: a loop closure on robot 3's key claiming
    robot 2 was streamed as robot 2's)."""
    parsed = keys.parse_event(key)
    field = _EVENT_ROBOT_FIELD.get(type(msg).__name__)
    if parsed is None or field is None:
        return False
    return int(getattr(msg, field)) == parsed[1]


def _decode(cls: type[E], sample: zenoh.Sample) -> E | None:
    """An event as ``cls``; None when it is malformed (the publisher's problem, not the
    page's) or names another robot than the key it came on."""
    try:
        msg = cls.FromString(sample.payload.to_bytes())
    except Exception:
        return None
    return msg if event_is_publishers(msg, str(sample.key_expr)) else None


class _Stream(queue.Queue[tuple[str, dict[str, Any]]]):
    """One reader's events; when full, the oldest is dropped and counted (the reader is told)."""

    def __init__(self) -> None:
        super().__init__(STREAM_QUEUE)
        self.dropped = 0

    def offer(self, item: tuple[str, dict[str, Any]]) -> None:
        while True:
            try:
                self.put_nowait(item)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self.get_nowait()
                    self.dropped += 1


def _scrape(url: str) -> list[tuple[str, dict[str, str], float]]:
    """The samples of one member's ``/metrics`` ([] when it does not answer in time)."""
    try:
        with urllib.request.urlopen(url, timeout=SCRAPE_TIMEOUT_S) as reply:
            text = reply.read(4 << 20).decode("utf-8", "replace")
        return [
            (s.name, dict(s.labels), float(s.value))
            for family in text_string_to_metric_families(text)
            for s in family.samples
        ]
    except Exception:
        return []


class _Server(ThreadingHTTPServer):
    """The stdlib's threaded server with a bound on connections (a thread each)."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler]) -> None:
        super().__init__(address, handler)
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self.slots.acquire(blocking=False):
            self.shutdown_request(request)  # full: closed unanswered, no thread made
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()


class _Handler(BaseHTTPRequestHandler):
    """GET / (the page), /api/state, /api/events; nothing else, and nothing without the token."""

    live: LiveView
    server_version = "swarmrec-live-view"
    protocol_version = "HTTP/1.1"
    timeout = IDLE_TIMEOUT_S  # a silent client (or one that stops reading) loses its connection

    def log_message(self, format: str, *args: Any) -> None:
        pass  # the gateway's own log says what matters; one line a poll would drown it

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        token = parse_qs(url.query).get("token", [""])[0]
        if not secrets.compare_digest(token, self.live.token):
            refused = b"this page needs the token printed with its address\n"
            self._send(HTTPStatus.FORBIDDEN, refused, "text/plain")
            return
        if url.path == "/":
            self._send(HTTPStatus.OK, PAGE.encode("utf-8"), "text/html; charset=utf-8")
        elif url.path == "/api/state":
            body = json.dumps(self.live.state()).encode("utf-8")
            self._send(HTTPStatus.OK, body, "application/json")
        elif url.path == "/api/events":
            self._events()
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")

    def _send(self, status: HTTPStatus, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        q = self.live.open_stream()
        if q is None:
            self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"too many event streams open\n", "text/plain")
            return
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            self.close_connection = True
            self._write(_lines([(": subscribed", None)]))
            while True:
                try:
                    kind, data = q.get(timeout=KEEPALIVE_S)
                except queue.Empty:
                    self._write(b": keepalive\n\n")
                    continue
                if kind == "end":
                    return
                if q.dropped:
                    data = {**data, "dropped": q.dropped}
                self._write(_lines([(f"event: {kind}", None), ("data", json.dumps(data))]))
        except (BrokenPipeError, ConnectionResetError, OSError):
            return  # the reader left
        finally:
            self.live.close_stream(q)

    def _write(self, data: bytes) -> None:
        self.wfile.write(data)
        self.wfile.flush()


def _lines(parts: Iterable[tuple[str, str | None]]) -> bytes:
    """One server-sent event: ``field: value`` lines, then a blank line."""
    out = [head if value is None else f"{head}: {value}" for head, value in parts]
    return ("\n".join(out) + "\n\n").encode("utf-8")
