"""A Foxglove WebSocket client in a few lines over `websockets`: what the Foxglove app does to show a live run
(`skinsafe run --foxglove`), for the bench's connected client and the tests.

The protocol (github.com/foxglove/foxglove-sdk, ws-protocol): the server sends JSON `serverInfo` and
`advertise` (channels: id, topic, encoding, schemaName, schema); the client sends `subscribe`
(subscription id -> channel id); each message then arrives binary: opcode 1, uint32 subscription id, uint64
log time (ns), the payload (here CDR).
"""
from __future__ import annotations

import asyncio
import json
import struct
import time

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1


async def collect(url: str, topics: list[str] | None, seconds: float, until: int | None = None) -> dict:
    """Connect to `url`, subscribe to `topics` (None: every advertised one), and gather what arrives for
    `seconds` (or until each topic has `until` messages, or the server closes): {"channels": {topic: advertised channel},
    "messages": {topic: [(log time ns, payload bytes)]}}."""
    import websockets

    channels, messages, subs = {}, {}, {}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                raw = await asyncio.wait_for(ws.recv(), left)
            except (TimeoutError, websockets.ConnectionClosed):  # the time is up, or the run ended
                break
            if isinstance(raw, str):
                op = json.loads(raw)
                if op.get("op") == "advertise":
                    new = [c for c in op["channels"] if topics is None or c["topic"] in topics]
                    for c in new:
                        channels[c["topic"]] = c
                        subs[len(subs) + 1] = c["topic"]
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()
                        if t in {c["topic"] for c in new}]}))
            elif raw[0] == MESSAGE_DATA:
                sub, ns = struct.unpack_from("<IQ", raw, 1)
                messages.setdefault(subs[sub], []).append((ns, bytes(raw[13:])))
                if until and topics and all(len(messages.get(t, ())) >= until for t in topics):
                    break
    return {"channels": channels, "messages": messages}


def watch(url: str, topics: list[str] | None, seconds: float, until: int | None = None) -> dict:
    """`collect` from a synchronous caller."""
    return asyncio.run(collect(url, topics, seconds, until))
