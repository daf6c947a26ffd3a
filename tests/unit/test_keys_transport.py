"""Key expressions and the zenoh flag set; a router and two peers exchange a wire message on loopback."""
import argparse
import json
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from quick_stream import keys
from quick_stream.motion import MotionEstimate
from quick_stream.transport import add_zenoh_args, config_from_args
from quick_stream.wire import decode, encode_motion


def test_keys_build_parse_and_reject():
    assert keys.key("cam0", "motion") == "quick/@v1/cam0/motion"
    assert keys.parse("quick/@v1/cam-2/frame") == ("cam-2", "frame")
    assert keys.all_streams("stats") == "quick/@v1/*/stats"
    for bad in ("", "a/b", "cam*", "x" * 65, "c@m"):
        with pytest.raises(ValueError, match="stream id"):
            keys.key(bad, "frame")
    with pytest.raises(ValueError, match="stage"):
        keys.key("cam0", "nosuch")
    with pytest.raises(ValueError, match="not a quick-stream key"):
        keys.parse("other/@v1/cam0/frame")


def parse(argv):
    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    return p.parse_args(argv)


def test_bad_flags_are_named():
    with pytest.raises(ValueError, match="--cfg"):
        config_from_args(parse(["--cfg", "novalue"]))
    with pytest.raises(ValueError, match="--config"):
        config_from_args(parse(["-c", "/does/not/exist.json5"]))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_router_and_peers_exchange_a_motion_message_on_loopback():
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(config_from_args(parse(["-m", "router", "-l", ep, "--no-multicast-scouting"])))
    sessions = [router]
    try:
        pub_s = zenoh.open(config_from_args(parse(["-e", ep, "--no-multicast-scouting"])))
        sub_s = zenoh.open(config_from_args(parse(["-e", ep, "--no-multicast-scouting"])))
        sessions += [pub_s, sub_s]
        sub = sub_s.declare_subscriber(keys.all_streams("motion"), zenoh.handlers.RingChannel(16))
        other = sub_s.declare_subscriber(keys.key("cam1", "motion"), zenoh.handlers.RingChannel(16))
        pub = pub_s.declare_publisher(keys.key("cam0", "motion"))
        m = MotionEstimate(7, 8, "se3", "exact", np.eye(4), np.zeros(6), True, zeta_bar=np.zeros(6))
        got = None
        deadline = time.time() + 10
        while got is None and time.time() < deadline:
            pub.put(encode_motion(m, "cam0"))
            time.sleep(0.05)
            got = sub.try_recv()
        assert got is not None, "no message through the router within 10 s"
        d = decode(got.payload.to_bytes())
        assert (d.type, d.stream, d.seq) == ("motion", "cam0", 7)
        assert keys.parse(str(got.key_expr)) == ("cam0", "motion")
        assert other.try_recv() is None  # another stream's subscriber sees nothing
    finally:
        for s in reversed(sessions):
            s.close()


def _args(argv: list[str]):
    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    return p.parse_args(argv)


def test_environment_overrides_and_cli_precedence(tmp_path):
    cfg = tmp_path / "c.json5"
    cfg.write_text('{mode: "peer", connect: {endpoints: ["tcp/10.0.0.9:7447"]}}')
    env = {"QUICK_STREAM_ZENOH_CONFIG": str(cfg), "QUICK_STREAM_ZENOH_MODE": "client",
           "QUICK_STREAM_ZENOH_CONNECT": "tcp/10.1.1.1:7447, tcp/10.1.1.2:7447"}
    c = config_from_args(_args([]), env)
    assert json.loads(c.get_json("mode")) == "client"
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/10.1.1.1:7447", "tcp/10.1.1.2:7447"]
    c = config_from_args(_args(["-m", "peer", "-e", "tcp/10.2.2.2:7447"]), env)  # flags beat the environment
    assert json.loads(c.get_json("mode")) == "peer"
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/10.2.2.2:7447"]


def test_peer_listens_where_other_hosts_can_reach_it():
    local = config_from_args(_args(["-e", "tcp/127.0.0.1:7447"]), {})
    remote = config_from_args(_args(["-e", "tcp/10.77.0.1:7447"]), {})
    assert json.loads(local.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(remote.get_json("listen/endpoints")) == ["tcp/0.0.0.0:0"]


def test_tls_flags_use_the_certificates_and_name_what_is_missing(tmp_path):
    with pytest.raises(ValueError, match="missing"):
        config_from_args(_args(["--tls-dir", str(tmp_path), "--tls-name", "flow"]), {})
    with pytest.raises(ValueError, match="go together"):
        config_from_args(_args(["--tls-dir", str(tmp_path)]), {})
    script = Path(__file__).resolve().parents[1] / "deploy" / "tls" / "make-certs.sh"
    subprocess.run(["bash", str(script), str(tmp_path / "c")], check=True, capture_output=True)
    c = config_from_args(_args(["-m", "client", "--tls-dir", str(tmp_path / "c" / "cam0" / "flow"), "--tls-name",
                                "flow"]), {})
    tls = json.loads(c.get_json("transport/link/tls"))
    assert tls["connect_certificate"].endswith("flow.pem") and tls["enable_mtls"] is True
    assert tls["root_ca_certificate"].endswith("ca.pem")
    # each party's folder holds its own key only, and no CA key is kept anywhere
    assert sorted(str(p.relative_to(tmp_path / "c")) for p in (tmp_path / "c").rglob("*.key")) == sorted(
        ["router/router.key", "monitor/monitor.key",
         *(f"cam0/{n}/{n}.key" for n in ("capture", "flow", "motion", "render", "recorder"))])
    assert all([k.name] == [p.name for p in k.parent.glob("*.key")] for k in (tmp_path / "c").rglob("*.key"))
    with pytest.raises(ValueError, match="missing .*make-certs.sh writes each party's files to"):
        config_from_args(_args(["--tls-dir", str(tmp_path / "c"), "--tls-name", "monitor"]), {})
    with pytest.raises(ValueError, match="missing .*make-certs.sh writes each service's files per stream: .*cam0/flow"):
        config_from_args(_args(["--tls-dir", str(tmp_path / "c"), "--tls-name", "flow"]), {})
    shared = tmp_path / "shared"  # a folder of every key: refused
    shared.mkdir()
    for n in ("flow", "render"):
        for f in (tmp_path / "c" / "cam0" / n).iterdir():
            (shared / f.name).write_bytes(f.read_bytes())
    with pytest.raises(ValueError, match=r"holds other private keys \(render.key\)"):
        config_from_args(_args(["--tls-dir", str(shared), "--tls-name", "flow"]), {})


def test_multicast_scouting_is_off_unless_asked_for(tmp_path):
    """Two deployments on one network must not find each other: every entry point's config has
    multicast scouting off unless a flag, a --cfg or the -c file turns it on."""
    def multicast(argv: list[str]) -> bool:
        return json.loads(config_from_args(_args(argv), {}).get_json("scouting/multicast/enabled"))

    assert multicast([]) is False
    assert multicast(["-m", "router", "-l", "tcp/127.0.0.1:0"]) is False
    assert multicast(["--no-multicast-scouting"]) is False
    assert multicast(["--multicast-scouting"]) is True
    assert multicast(["--cfg", "scouting/multicast/enabled:true"]) is True
    on = tmp_path / "on.json5"
    on.write_text('{ mode: "peer", scouting: { multicast: { enabled: true } } }')
    plain = tmp_path / "plain.json5"
    plain.write_text('{ mode: "peer" /* multicast left to the default */ }')
    assert multicast(["-c", str(on)]) is True
    assert multicast(["-c", str(plain)]) is False
    with pytest.raises(ValueError, match="contradict"):
        config_from_args(_args(["--multicast-scouting", "--no-multicast-scouting"]), {})
