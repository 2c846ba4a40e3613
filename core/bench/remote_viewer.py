"""A browser on another computer, as the robot PC sees it (`bench runtime --view alternating-remote`, the view's
tests): the page's websocket opened as viser's page opens it (its subprotocol, then its camera, after which viser
counts a client) and every message the page sends taken, nothing drawn. The robot PC keeps its whole side of a
page viewed elsewhere (the stream's publisher, the page's process, viser's sends) without a browser drawing on
its cores.

`python -m skinsafe.core.bench.remote_viewer URL`: until the page closes (or SIGTERM).
"""
from __future__ import annotations

import sys

import msgspec
import viser
from viser._messages import ViewerCameraMessage
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.sync.client import ClientConnection, connect


def open_page(url: str, timeout_s: float = 30.0) -> ClientConnection:
    """The page at `url` (http:// or ws://) opened as a browser opens it; a context manager."""
    ws = connect(url.replace("http://", "ws://", 1), subprotocols=[f"viser-v{viser.__version__}"],
                 open_timeout=timeout_s, max_size=None, max_queue=None)  # the whole scene, as a browser takes it
    camera = ViewerCameraMessage((1.0, 0.0, 0.0, 0.0), (2.0, 0.0, 1.0), 1.0, 0.01, 100.0, 800, 1200,
                                 (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
    return ws


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m skinsafe.core.bench.remote_viewer URL", file=sys.stderr)
        return 2
    try:
        ws = open_page(argv[0])
    except (OSError, TimeoutError, WebSocketException) as e:
        print(f"remote viewer: cannot open {argv[0]} ({e})", file=sys.stderr)
        return 2
    with ws:
        try:
            while True:
                ws.recv()
        except ConnectionClosed:
            return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
