"""The live view (localization.ros.live_view): a Foxglove WebSocket server on a free loopback port,
a plain WebSocket client that reads the advertised channels, subscribes and receives the data."""
from __future__ import annotations

import asyncio
import json
import struct
import threading
import time

import numpy as np
import pytest
import websockets  # a [dev] dependency (requirements.txt)
from helpers import corridor_map

from localization.core.localizer import Localizer
from localization.core.localizer.timeline import PoseEstimate
from localization.core.scan import ScanData
from localization.ros.live_view import TOPICS, LiveView, LiveViewError

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # the SDK's current name, then the older one


class _FakeLocalizer:
    """The part of Localizer's public API the live view reads (checked against the class below)."""

    ready = True
    laser_offset = np.array([0.25, 0.0, 0.0])

    def __init__(self):
        self.pose = np.array([2.0, 1.5, 0.0])

    def scan_time(self, scan):
        return scan.stamp + 0.0125

    def estimate_at(self, t):
        return PoseEstimate(stamp=t, pose=self.pose + [0.5 * t, 0.0, 0.0], covariance=np.eye(3) * 1e-4)

    def particles(self):
        return np.tile(self.pose, (2000, 1))


def test_fake_localizer_matches_the_real_api():
    for name in ("ready", "laser_offset", "scan_time", "estimate_at", "particles"):
        assert hasattr(Localizer, name), name
    assert callable(Localizer.particles) and callable(Localizer.estimate_at)


def _scan(t: float) -> ScanData:
    return ScanData(stamp=t, ranges=np.r_[np.full(99, 1.5), np.inf], angle_min=-2.0, angle_max=2.0,
                    angle_increment=4.0 / 99, range_min=0.05, range_max=10.0, frame_id="laser")


async def _client(port: int, want: set, seconds: float = 5.0, at_least: dict | None = None) -> tuple[dict, dict, str]:
    """Connect, read the advertisements, subscribe to everything, count messages per topic until
    each topic in ``want`` has one and each topic of ``at_least`` its count (or ``seconds`` pass).
    Returns (channels by topic, counts, negotiated subprotocol)."""
    at_least = at_least or {}
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        channels: dict = {}
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not set(TOPICS.values()) <= set(channels):
            msg = await asyncio.wait_for(ws.recv(), timeout=seconds)
            if isinstance(msg, str):
                doc = json.loads(msg)
                if doc.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in doc["channels"]})
        by_sub = {k: topic for k, topic in enumerate(sorted(channels))}
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": channels[topic]["id"]} for k, topic in by_sub.items()]}))
        counts: dict = {}
        payloads: dict = {}
        while time.monotonic() < deadline and not (want <= set(counts) and all(
                counts.get(topic, 0) >= n for topic, n in at_least.items())):
            try:
                msg = await asyncio.wait_for(ws.recv(), timeout=0.5)
            except asyncio.TimeoutError:
                continue
            if isinstance(msg, bytes) and msg[0] == 0x01:  # message data: opcode, subscription id, log time
                sub, log_time = struct.unpack_from("<IQ", msg, 1)
                topic = by_sub[sub]
                counts[topic] = counts.get(topic, 0) + 1
                payloads.setdefault(topic, (log_time, msg[13:]))
        return channels, {"counts": counts, "payloads": payloads}, ws.subprotocol


def test_serves_every_channel_and_delivers_after_subscribing():
    with LiveView(port=0, rate=0.0) as live:
        assert live.port > 0 and live.host == "127.0.0.1"
        live.set_map(corridor_map())
        live.set_reference([0.0, 0.5, 1.0], [[2.0, 1.5, 0.0], [2.5, 1.5, 0.0], [3.0, 1.5, 0.0]])
        fake = _FakeLocalizer()
        stop = threading.Event()

        def feed():  # the replay's hook, called after each scan, until the client has seen enough
            k = 0
            while not stop.is_set():
                live(_scan(0.025 * k), fake)
                k += 1
                time.sleep(0.02)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            streaming = {"/scan": 2, "/pf/pose": 2}  # delivered again and again, not only once
            channels, got, proto = asyncio.run(_client(live.port, set(TOPICS.values()), at_least=streaming))
        finally:
            stop.set()
            feeder.join(5)
    assert proto in SUBPROTOCOLS
    assert set(TOPICS.values()) <= set(channels)
    schemas = {topic: channels[topic]["schemaName"] for topic in TOPICS.values()}
    assert schemas == {"/map": "foxglove.Grid", "/scan": "foxglove.LaserScan", "/pf/particles": "foxglove.PosesInFrame",
                       "/pf/pose": "foxglove.PoseInFrame", "/pf/track": "foxglove.SceneUpdate",
                       "/reference/track": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransforms"}
    counts = got["counts"]
    # the map and the reference track were set before the client came: sent again to it
    assert set(TOPICS.values()) <= set(counts), counts
    assert counts["/scan"] >= 2 and counts["/pf/pose"] >= 2
    # the map's payload is the int8 occupancy grid (the grid's bytes are in the message)
    m = corridor_map()
    _, payload = got["payloads"]["/map"]
    assert np.ascontiguousarray(m.data, dtype=np.int8).tobytes() in payload


def test_estimate_payload_is_the_pose_fed_in():
    import foxglove.messages as fm

    with LiveView(port=0) as live:
        holder: dict = {}

        def run():
            holder["r"] = asyncio.run(_client(live.port, {"/pf/pose"}))

        client = threading.Thread(target=run)
        client.start()
        deadline = time.monotonic() + 5
        while client.is_alive() and time.monotonic() < deadline:
            live.publish_estimate(12.5, (1.0, 2.0, 0.5))
            time.sleep(0.05)
        client.join(5)
    log_time, payload = holder["r"][1]["payloads"]["/pf/pose"]
    assert log_time == 12_500_000_000  # the stamp the pose describes, in ns
    q = np.array([0.0, 0.0, np.sin(0.25), np.cos(0.25)])
    expected = fm.PoseInFrame(timestamp=fm.Timestamp.from_epoch_secs(12.5), frame_id="map", pose=fm.Pose(
        position=fm.Vector3(x=1.0, y=2.0, z=0.0), orientation=fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
    assert payload == expected.encode()


def test_bad_estimate_is_not_sent_and_port_in_use_is_one_error():
    with LiveView(port=0) as live:
        live.publish_estimate(1.0, (np.nan, 0.0, 0.0))  # dropped, no exception
        assert live._track_t == []
        with pytest.raises(LiveViewError) as exc:
            LiveView(port=live.port)
        assert str(live.port) in str(exc.value) and "\n" not in str(exc.value)


def test_pacing_follows_the_stamps():
    with LiveView(port=0, rate=4.0) as live:
        t0 = time.monotonic()
        for k in range(5):
            live.pace(0.1 * k)  # 0.4 s of data at 4x: 0.1 s of wall time
        elapsed = time.monotonic() - t0
    assert 0.08 <= elapsed < 1.0


def test_a_late_viewer_gets_the_last_state():
    with LiveView(port=0) as live:
        live.set_map(corridor_map())
        live.publish_estimate(3.0, (2.0, 1.5, 0.1))
        live.publish_particles(3.0, np.tile([2.0, 1.5, 0.1], (50, 1)))
        _, got, _ = asyncio.run(_client(live.port, {"/map", "/pf/pose", "/pf/particles", "/tf"}))
    assert {"/map", "/pf/pose", "/pf/particles", "/tf"} <= set(got["counts"]), got["counts"]


def test_replay_foxglove_serves_the_run_and_keeps_the_result(monkeypatch, tmp_path):
    """``localization-replay --foxglove 0 --rate 0``: the live view is fed during the replay and,
    at the end, holds the reference (here: the ground truth) and the final state."""
    from localization.eval.datasets import sim_bag
    from localization.tools import replay

    held = {}

    def hold(live):  # instead of waiting for Ctrl-C
        held["kept"] = set(live._kept)
        held["port"] = live.port
        live.close()
        return 0
    monkeypatch.setattr(replay, "hold_live_view", hold)
    bag = sim_bag("trial1_noise0", duration=3.0)
    rc = replay.main([str(bag), "--map", "stata_basement", "--params", "params", "--particles", "200",
                      "--foxglove", "0", "--rate", "0", "--no-plots", "--quiet", "--out", str(tmp_path / "out")])
    assert rc == 0 and held["port"] > 0
    assert {"/map", "/pf/pose", "/pf/particles", "/pf/track", "/reference/track", "/tf"} <= held["kept"]


def test_the_node_serves_the_live_view_with_foxglove_port(runner):
    """foxglove_port 0: the node starts the live view on a free loopback port; a client sees its channels
    and gets the map the node received."""
    import node_harness as h
    r = runner(foxglove_port=0)
    view = r.node.live_view
    assert view is not None and view.host == "127.0.0.1" and view.port > 0
    r.send_map(h.map_msg("basement_fixed"))
    deadline = time.monotonic() + 60.0
    while not r.node.localizer.has_map and time.monotonic() < deadline:
        r.settle(0.2)
    channels, got, _ = asyncio.run(_client(view.port, {"/map"}))
    assert set(TOPICS.values()) <= set(channels)
    assert got["counts"].get("/map", 0) >= 1
