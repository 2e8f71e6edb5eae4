"""A bounded HTTP server on 127.0.0.1 for download tests (never the internet)."""

from __future__ import annotations

import http.server
import threading

MAX_REQUESTS = 30
LIFETIME_S = 30.0


class LocalServer:
    """A bounded HTTP server: ``routes[path] = (status, body, mode)``, mode "ok" or "truncate"
    (announce the full length, send half, close)."""

    def __init__(self) -> None:
        self.routes: dict[str, tuple[int, bytes, str]] = {}
        self.requests: list[str] = []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                server.requests.append(self.path)
                if len(server.requests) > MAX_REQUESTS:
                    self.send_error(503, "request budget of the test server used up")
                    threading.Thread(target=server.httpd.shutdown, daemon=True).start()
                    return
                status, body, mode = server.routes.get(self.path, (404, b"not found", "ok"))
                self.send_response(status)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body if mode == "ok" else body[: len(body) // 2])
                if mode == "truncate":
                    self.close_connection = True

            def log_message(self, format: str, *args: object) -> None:
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.timer = threading.Timer(LIFETIME_S, self.httpd.shutdown)
        self.timer.daemon = True

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}{path}"

    def start(self) -> LocalServer:
        self.thread.start()
        self.timer.start()
        return self

    def stop(self) -> None:
        self.timer.cancel()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)
