"""The container health check reads the service's own ready gauge."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer

import pytest

from swarmrec.healthcheck import is_ready, main


@pytest.mark.parametrize(
    ("text", "ready"),
    [
        ("# HELP swarmrec_service_ready x\nswarmrec_service_ready 1.0\n", True),
        ("swarmrec_service_ready 0.0\n", False),
        ("swarmrec_service_ready_other 1.0\n", False),
        ("swarmrec_service_ready nan\n", False),
        ("swarmrec_service_ready garbage\n", False),
        ("", False),
    ],
)
def test_is_ready_only_when_the_gauge_is_one(text: str, ready: bool) -> None:
    assert is_ready(text) is ready


@pytest.fixture
def metrics_server() -> Iterator[tuple[HTTPServer, list[str]]]:
    page = ["swarmrec_service_ready 1.0\n"]

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = page[0].encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_args: object) -> None:
            pass

    server = HTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server, page
    server.shutdown()
    server.server_close()


def test_healthcheck_passes_on_a_ready_service_and_fails_otherwise(
    metrics_server: tuple[HTTPServer, list[str]],
) -> None:
    server, page = metrics_server
    port = str(server.server_address[1])
    assert main(["--port", port]) == 0
    page[0] = "swarmrec_service_ready 0.0\n"
    assert main(["--port", port]) == 1


def test_healthcheck_fails_when_nothing_listens(refused_port: int) -> None:
    assert main(["--port", str(refused_port), "--timeout", "0.5"]) == 1
