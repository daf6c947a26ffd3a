"""The TLS router's access control as zenoh enforces it (quick_stream/stream/acl.py; the rules themselves are
checked statically in tests/unit/test_deploy_files.py): on loopback, a router with the generated
configuration for streams cam0 and cam1 and sessions holding make-certs.sh certificates.

Each refusal is shown against an allowed message sent after it on the same session: once the
allowed one has arrived, the refused one, sent before it on the same link, would have too.
"""
from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from quick_stream.stream import keys
from quick_stream.stream.acl import SERVICES, access_control, common_name, router_config_text
from quick_stream.stream.launcher import free_port
from quick_stream.stream.transport import session_config

ROOT = Path(__file__).resolve().parents[2]


class Seen:
    def __init__(self) -> None:
        self.keys: list[str] = []
        self.cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.cond:
            self.keys.append(str(sample.key_expr))
            self.cond.notify_all()

    def wait_for(self, key: str, timeout: float = 30) -> list[str]:
        with self.cond:
            assert self.cond.wait_for(lambda: key in self.keys, timeout), (key, self.keys)
            return list(self.keys)


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    d = tmp_path_factory.mktemp("acl")
    subprocess.run(["bash", str(ROOT / "deploy" / "tls" / "make-certs.sh"), "--streams", "cam0,cam1",
                    "--all-streams-recorder", str(d / "certs")], check=True, capture_output=True)
    (d / "router.json5").write_text(router_config_text(["cam0", "cam1"]))
    ep = f"tls/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "quick_stream", "router", "-c", str(d / "router.json5"), "-l", ep,
                             "--tls-dir", str(d / "certs" / "router"), "--tls-name", "router"],
                            stderr=subprocess.PIPE, text=True)
    assert "up" in proc.stderr.readline()  # the router says so once it listens
    sessions: list[zenoh.Session] = []

    def open_as(party: str, stream: str | None = None) -> zenoh.Session:
        folder = d / "certs" / (party if stream is None else f"{stream}/{party}")
        sessions.append(zenoh.open(session_config(ep, "client", str(folder), party)))
        return sessions[-1]

    open_as.certs = d / "certs"
    yield open_as
    for s in sessions:
        s.close()
    proc.terminate()
    proc.wait(10)


def test_liveliness_tokens_only_as_itself(router):
    monitor, flow = router("monitor"), router("flow", "cam0")
    seen = Seen()
    sub = monitor.liveliness().declare_subscriber(f"{keys.PREFIX}/*/health/*", seen, history=True)
    forged = [flow.liveliness().declare_token(keys.health_key("cam0", "render")),  # another service's
              flow.liveliness().declare_token(keys.health_key("cam1", "flow"))]  # another stream's
    own = flow.liveliness().declare_token(keys.health_key("cam0", "flow"))
    assert seen.wait_for(keys.health_key("cam0", "flow")) == [keys.health_key("cam0", "flow")]
    for t in (*forged, own, sub):
        t.undeclare()


def test_cursor_answered_only_as_itself(router):
    flow, capture = router("flow", "cam0"), router("capture", "cam0")
    queryables = [flow.declare_queryable(keys.cursor_key("cam0", name),
                                         lambda q, name=name: q.reply(keys.cursor_key("cam0", name), name.encode()))
                  for name in ("render", "flow")]  # answering as render is refused: only flow's answer comes
    deadline = time.monotonic() + 30
    while True:  # until the queryable is known to the router (a query right after declaring may miss it)
        got = [(str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in
               capture.get(keys.cursor_key("cam0"), target=zenoh.QueryTarget.ALL,
                           consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0) if r.ok is not None]
        if got or time.monotonic() > deadline:
            break
    assert got == [(keys.cursor_key("cam0", "flow"), b"flow")]
    for q in queryables:
        q.undeclare()


def test_frames_only_of_its_own_stream(router):
    monitor, capture, other = router("monitor"), router("capture", "cam0"), router("capture", "cam1")
    seen = Seen()
    sub = monitor.declare_subscriber(keys.all_streams("frame"), seen)
    pubs = {(s, k): s.declare_publisher(keys.key(k, "frame")) for s in (capture, other) for k in ("cam0", "cam1")}
    deadline = time.monotonic() + 30
    while not all(p.matching_status.matching for (s, k), p in pubs.items()) and time.monotonic() < deadline:
        time.sleep(0.01)  # until the publishers know the monitor's subscriber (a client sends only then)
    pubs[(capture, "cam1")].put(b"cam0's capture on cam1")  # refused
    pubs[(other, "cam0")].put(b"cam1's capture on cam0")  # refused
    pubs[(other, "cam1")].put(b"cam1's capture on cam1")
    seen.wait_for(keys.key("cam1", "frame"))
    pubs[(capture, "cam0")].put(b"cam0's capture on cam0")
    assert seen.wait_for(keys.key("cam0", "frame")) == [keys.key("cam1", "frame"), keys.key("cam0", "frame")]
    sub.undeclare()


def test_make_certs_issues_the_access_controls_common_names(router):
    """make-certs.sh --streams: a folder per party holding its own key only, with the common name the
    access control expects; no CA key anywhere."""
    certs = router.certs
    cns = {}
    for pem in certs.glob("**/*.pem"):
        if pem.name == "ca.pem":
            continue
        folder = pem.parent
        assert sorted(p.name for p in folder.iterdir()) == sorted(["ca.pem", pem.name, pem.stem + ".key"]), folder
        subject = subprocess.run(["openssl", "x509", "-in", str(pem), "-noout", "-subject"], capture_output=True,
                                 text=True, check=True).stdout
        cns[str(folder.relative_to(certs))] = subject.strip().rpartition("CN")[2].lstrip(" =")
    want = {f"{st}/{s}": common_name(s, st) for st in ("cam0", "cam1") for s in SERVICES}
    want.update({"router": "quick-router", "monitor": "quick-monitor", "recorder": "quick-recorder"})
    assert cns == want
    acl_cns = {cn for s in access_control(["cam0", "cam1"])["subjects"] for cn in s["cert_common_names"]}
    assert acl_cns == set(want.values()) - {"quick-router"}
    assert not list(certs.glob("**/ca.key"))
