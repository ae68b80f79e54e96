"""The live view (`swarmloc run --view PORT`): netsim serves the recording's channels over the
Foxglove WebSocket protocol on 127.0.0.1. A plain WebSocket client (websockets) sees the
channels advertised, subscribes, decodes the messages with the schemas the server sent, and
sees a fault injected into the running swarm arrive on /faults and in the scene."""

import base64
import json
import struct
import time

import pytest
from conftest import framed, free_port
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from websockets.sync.client import connect

from swarmloc.experiment import recording as R
from swarmloc.experiment import scenario as S

pytestmark = pytest.mark.slow


def _decoder(channel: dict):
    schema = Schema(id=channel["id"], name=channel["schemaName"], encoding=channel["schemaEncoding"],
                    data=base64.b64decode(channel["schema"]))
    return DecoderFactory().decoder_for(channel["encoding"], schema)


def test_live_view_over_websocket(cli, tmp_path):
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 200.0, "clock.mode": "realtime", "clock.speed": 4.0})
    (tmp_path / "live.yaml").write_text(sc.to_yaml())
    port = free_port()
    run = cli.start_run("live.yaml", tmp_path / "run", "--view", str(port))
    cli.wait_tick(2, run)
    # The layout a live viewer imports is there while the run goes, framed on the start.
    cam = json.loads((tmp_path / "run" / R.LAYOUT).read_text())["configById"]["3D!swarmloc"]["cameraState"]
    assert framed(cam, [a.start[:2] for a in sc.world.agents])
    channels: dict[int, dict] = {}
    subscribed: dict[int, dict] = {}
    seen: dict[str, list] = {}
    injected = False
    deadline = time.monotonic() + 60
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
        while time.monotonic() < deadline and not any("cut" in m.message for m in seen.get("/faults", [])):
            try:
                msg = ws.recv(timeout=1.0)
            except TimeoutError:
                continue
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["op"] == "advertise":
                    new = [c for c in m["channels"] if c["id"] not in channels]
                    channels.update({c["id"]: c for c in new})
                    subs = [c for c in new if c["topic"] in ("/scene", "/faults")]
                    for c in subs:
                        subscribed[c["id"]] = {"channel": c, "decode": _decoder(c)}
                    if subs:
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c["id"], "channelId": c["id"]}
                                                                                 for c in subs]}))
                continue
            assert msg[0] == 1  # message data: opcode, subscription id, log time, payload
            sub, _ = struct.unpack_from("<IQ", msg, 1)
            s = subscribed[sub]
            seen.setdefault(s["channel"]["topic"], []).append(s["decode"](msg[13:]))
            if not injected and len(seen.get("/scene", [])) >= 3:
                p = cli.control("inject", "cut", "1", "2")
                assert p.returncode == 0, p.stderr
                injected = True
    topics = {c["topic"]: c for c in channels.values()}
    assert topics["/scene"]["schemaName"] == "foxglove.SceneUpdate"
    assert topics[f"swarmloc/{cli.swarm}/agent/1/sensors"]["encoding"] == "msgpack"
    assert any(t.startswith("/metrics/ukf-dcl/") for t in topics)
    faults = [m.message for m in seen.get("/faults", [])]
    assert any(": cut link=[1,2]" in f and "(live)" in f for f in faults), faults
    scene = seen["/scene"][-1]
    ids = {e.id for e in scene.entities}
    assert {"truth", "estimate/ukf-dcl"} <= ids
    truth = next(e for e in scene.entities if e.id == "truth")
    assert len(truth.spheres) == 4
    cli.control("stop")
    run.wait(60)
