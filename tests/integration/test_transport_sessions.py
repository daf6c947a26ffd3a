"""Zenoh sessions on loopback with the standard flags, and TLS certificates from deploy/tls/make-certs.sh."""
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from quick_stream.core.motion import MotionEstimate
from quick_stream.stream import keys
from quick_stream.stream.launcher import free_port
from quick_stream.stream.transport import config_from_args
from quick_stream.stream.wire import decode, encode_motion
from tests.unit.test_keys_transport import _args, parse


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


def test_tls_flags_use_the_certificates_and_name_what_is_missing(tmp_path):
    with pytest.raises(ValueError, match="missing"):
        config_from_args(_args(["--tls-dir", str(tmp_path), "--tls-name", "flow"]), {})
    with pytest.raises(ValueError, match="go together"):
        config_from_args(_args(["--tls-dir", str(tmp_path)]), {})
    script = Path(__file__).resolve().parents[2] / "deploy" / "tls" / "make-certs.sh"
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
