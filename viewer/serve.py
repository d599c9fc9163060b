"""Serve a viewer bundle on localhost with the standard library's HTTP server (no network beyond loopback)."""

from __future__ import annotations

import functools
import http.server
import sys
from pathlib import Path


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Static files of one folder; no request log; never cached (a rebuilt bundle shows at once)."""

    extensions_map = {
        **http.server.SimpleHTTPRequestHandler.extensions_map,
        ".js": "text/javascript",
        ".bin": "application/octet-stream",
        ".json": "application/json",
    }

    def end_headers(self) -> None:
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, format: str, *args) -> None:  # noqa: A002 - the base class's signature
        return


def make_server(
    folder: str | Path, port: int = 0, host: str = "127.0.0.1"
) -> http.server.ThreadingHTTPServer:
    """An HTTP server of `folder` bound to host:port (port 0: a free one; see `server_address`)."""
    handler = functools.partial(_Handler, directory=str(folder))
    return http.server.ThreadingHTTPServer((host, port), handler)


def serve(folder: str | Path, port: int, host: str = "127.0.0.1") -> None:
    """Serve `folder` until interrupted, printing the address to open."""
    with make_server(folder, port, host) as httpd:
        url = f"http://{host}:{httpd.server_address[1]}/"
        print(f"lightstage view: open {url} (serving {folder}; Ctrl-C stops)", file=sys.stderr, flush=True)
        try:
            httpd.serve_forever()
        except KeyboardInterrupt:
            print("lightstage view: stopped", file=sys.stderr)
