"""The pipeline across separate network hosts (docs/deployment.md, "Camera host + compute host"):
Linux network namespaces joined by veth links.

Four namespaces, addresses only inside them: ``hub`` (a bridge, 10.77.x.1, the router),
``cam`` (.2, capture), ``compute`` (.3, flow and motion), ``view`` (.4, render and recorder).
The stabilized frames must equal the single-host result; then the same with TLS (mutual
authentication) and the router's access control, where a session without a valid
certificate, or publishing on a key its certificate does not allow (another stage, or another
stream: certificates are per stream), gets nothing through.
Needs root (CAP_NET_ADMIN) for ``ip netns``, which these machines grant.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.helpers import offline_images

from quick_stream.stream.launcher import ServiceSpec, Supervisor

ROOT = Path(__file__).resolve().parents[2]
SPEC = "synthetic:frames=60,width=320,height=240"
PROBE = str(ROOT / "tests" / "tools" / "netns_probe.py")


def sh(*cmd: str) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {r.stderr.strip()} (network namespaces need root / CAP_NET_ADMIN)")


class Hosts:
    """hub (bridge + router address), cam, compute, view; torn down on exit."""

    def __init__(self) -> None:
        tag = f"{os.getpid() % 100000}"
        self.net = f"10.{77 + os.getpid() % 100}.0"
        self.ns = {n: f"qs-{n}-{tag}" for n in ("hub", "cam", "compute", "view")}
        self.addr = {"hub": f"{self.net}.1", "cam": f"{self.net}.2", "compute": f"{self.net}.3", "view": f"{self.net}.4"}
        self.tag = tag

    def __enter__(self) -> "Hosts":
        hub = self.ns["hub"]
        for ns in self.ns.values():
            sh("ip", "netns", "add", ns)
            sh("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")
        sh("ip", "netns", "exec", hub, "ip", "link", "add", "br0", "type", "bridge")
        sh("ip", "netns", "exec", hub, "ip", "addr", "add", f"{self.addr['hub']}/24", "dev", "br0")
        sh("ip", "netns", "exec", hub, "ip", "link", "set", "br0", "up")
        for i, host in enumerate(("cam", "compute", "view")):
            a, b = f"qa{i}{self.tag}", f"qb{i}{self.tag}"
            sh("ip", "link", "add", a, "type", "veth", "peer", "name", b)
            sh("ip", "link", "set", a, "netns", hub)
            sh("ip", "link", "set", b, "netns", self.ns[host])
            sh("ip", "netns", "exec", hub, "ip", "link", "set", a, "master", "br0")
            sh("ip", "netns", "exec", hub, "ip", "link", "set", a, "up")
            sh("ip", "netns", "exec", self.ns[host], "ip", "addr", "add", f"{self.addr[host]}/24", "dev", b)
            sh("ip", "netns", "exec", self.ns[host], "ip", "link", "set", b, "up")
        return self

    def __exit__(self, *exc) -> None:
        for ns in self.ns.values():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)

    def prefix(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns[host]]

    def probe(self, host: str, *args: str, timeout: float = 60) -> dict:
        r = subprocess.run([*self.prefix(host), sys.executable, PROBE, *args], capture_output=True, text=True,
                           timeout=timeout)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def hosts():
    with Hosts() as h:
        yield h


@pytest.fixture(scope="module")
def single_host() -> dict[int, np.ndarray]:
    """The single-host result (equal, bit for bit, to the services on one host: tests/integration/test_services_e2e.py)."""
    return offline_images(SPEC)


def run_pipeline(h: Hosts, out: Path, router: list[str], zflags: dict[str, list[str]]) -> Supervisor:
    """Router on hub, capture on cam, flow + motion on compute, render + recorder on view."""
    specs = [
        ServiceSpec("router", ["-m", "quick_stream", "router", *router], prefix=h.prefix("hub")),
        ServiceSpec("recorder", ["-m", "quick_stream.services.recorder", *zflags["recorder"],
                                 "--output", str(out / "rec.mcap")],
                    prefix=h.prefix("view")),
        ServiceSpec("render", ["-m", "quick_stream.services.render", *zflags["render"], "--png", str(out / "png"),
                               "--color", "raw"],
                    prefix=h.prefix("view")),
        ServiceSpec("flow", ["-m", "quick_stream.services.flow", *zflags["flow"]], prefix=h.prefix("compute")),
        ServiceSpec("motion", ["-m", "quick_stream.services.motion", *zflags["motion"]], prefix=h.prefix("compute")),
        ServiceSpec("capture", ["-m", "quick_stream.services.capture", *zflags["capture"], "--source", SPEC,
                                "--color", "raw", "--pace", "fast", "--wait-for", "recorder,render,flow,motion", "--wait-timeout", "60"],
                    prefix=h.prefix("cam"), may_finish=True),
    ]
    sup = Supervisor(specs, out / "logs", max_restarts=0)
    sup.start("router")
    time.sleep(1.0)
    for s in specs[1:]:
        sup.start(s.name)
    deadline = time.monotonic() + 120
    render_log = out / "logs" / "render.log"
    while time.monotonic() < deadline:
        time.sleep(0.5)
        sup.poll()
        if render_log.exists() and "end of stream" in render_log.read_text():
            break
    else:
        logs = {p.name: p.read_text()[-800:] for p in (out / "logs").glob("*.log")}
        sup.stop()
        pytest.fail(f"pipeline across namespaces did not finish: {logs}")
    return sup


def assert_same(out: Path, single_host: dict[int, np.ndarray]) -> None:
    got = {int(p.stem): cv2.imread(str(p)) for p in sorted((out / "png").glob("*.png"))}
    assert sorted(got) == sorted(single_host)
    assert [s for s in single_host if not np.array_equal(got[s], single_host[s])] == []


def test_pipeline_across_three_hosts_matches_single_host(hosts, single_host, tmp_path):
    router_ep = f"tcp/{hosts.addr['hub']}:7447"
    z = ["-e", router_ep, "--no-multicast-scouting"]  # peers: connect to the router, listen on their host
    sup = run_pipeline(hosts, tmp_path, ["-l", router_ep, "--no-multicast-scouting"],
                       {s: z for s in ("recorder", "render", "flow", "motion", "capture")})
    codes = sup.stop(["capture", "flow", "motion", "render", "recorder", "router"])
    assert all(c == 0 for c in codes.values()), codes
    assert_same(tmp_path, single_host)


@pytest.fixture(scope="module")
def certs(tmp_path_factory, hosts):
    """Certificates for streams cam0 (the pipeline) and cam9 (the probes), and a router configuration
    whose access control covers both (`quick-stream acl`; deploy/zenoh/router-tls.json5 is cam0's)."""
    d = tmp_path_factory.mktemp("certs")
    for name in ("good", "rogue"):
        subprocess.run(["bash", str(ROOT / "deploy" / "tls" / "make-certs.sh"), "--streams", "cam0,cam9",
                        str(d / name), hosts.addr["hub"]], check=True, capture_output=True)
    subprocess.run([sys.executable, "-m", "quick_stream", "acl", "--streams", "cam0,cam9", "--output",
                    str(d / "router-tls.json5")], check=True)
    return d


def test_tls_and_access_control_across_hosts(hosts, single_host, certs, tmp_path):
    ep = f"tls/{hosts.addr['hub']}:7447"
    good = str(certs / "good")
    router = ["-c", str(certs / "router-tls.json5"), "-l", ep, "--tls-dir", f"{good}/router", "--tls-name", "router"]
    z = {s: ["-m", "client", "-e", ep, "--no-multicast-scouting", "--tls-dir", f"{good}/cam0/{s}", "--tls-name", s]
         for s in ("recorder", "render", "flow", "motion", "capture")}
    sup = run_pipeline(hosts, tmp_path, router, z)
    try:
        assert_same(tmp_path, single_host)  # everything allowed still flows, bit for bit
        key = "quick/@v1/cam9/frame"
        # control: a subscriber (monitor certificate) sees what cam9's capture certificate publishes
        # the subscriber listens until the publisher has finished (communicate() closes its stdin)
        listen = subprocess.Popen([*hosts.prefix("view"), sys.executable, PROBE, "sub", ep, key, "20", f"{good}/monitor",
                                   "monitor"],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert "subscribed" in listen.stdout.readline()  # wait for the subscriber itself, not a clock
        sent = hosts.probe("cam", "pub", ep, key, "1.5", f"{good}/cam9/capture", "capture")
        got = json.loads(listen.communicate(timeout=30)[0].strip().splitlines()[-1])
        assert sent["opened"] and sent["sent"] > 10 and got["received"] > 10
        # a certificate from another CA does not get in at all
        rogue = hosts.probe("cam", "pub", ep, key, "1.0", str(certs / "rogue" / "cam9" / "capture"), "capture")
        assert not rogue["opened"] or rogue["sent"] == 0, rogue
        # valid certificates publishing where their name is not allowed get nothing through: the monitor, a
        # capture on another stage, a flow on frames (another stream's capture: tests/integration/test_acl.py)
        for who, where in (("monitor", key), ("cam9/capture", "quick/@v1/cam9/correction"), ("cam9/flow", key)):
            listen = subprocess.Popen([*hosts.prefix("view"), sys.executable, PROBE, "sub", ep, where, "20",
                                       f"{good}/monitor", "monitor"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      text=True)
            assert "subscribed" in listen.stdout.readline()
            sent = hosts.probe("compute", "pub", ep, where, "1.5", f"{good}/{who}", who.rpartition("/")[2])
            got = json.loads(listen.communicate(timeout=30)[0].strip().splitlines()[-1])
            assert sent["opened"] and sent["sent"] > 10, (who, sent)
            assert got["received"] == 0, (who, where, got)
        # history: a restarted service reads what it missed from its inputs' publishers' caches (the ACL
        # denied it: under TLS a restarted capture renumbered from 0 and flow and render refused every frame)
        cache = subprocess.Popen([*hosts.prefix("cam"), sys.executable, PROBE, "cache", ep, key, "30",
                                  f"{good}/cam9/capture", "capture"], stdout=subprocess.PIPE, text=True)
        try:
            assert "published" in cache.stdout.readline()
            got = hosts.probe("compute", "history", ep, key, "10:20", f"{good}/cam9/flow", "flow")
            assert got["opened"] and got["received"] == 20, got  # the whole cache, as on TCP
            got = hosts.probe("view", "history", ep, key, "3", f"{good}/monitor", "monitor")
            assert got["received"] == 0, got  # the monitor only watches live data
        finally:
            cache.kill()
        # without TLS (plain TCP to the TLS port) nothing connects
        plain = hosts.probe("cam", "pub", f"tcp/{hosts.addr['hub']}:7447", key, "1.0")
        assert not plain["opened"] or plain["sent"] == 0
    finally:
        codes = sup.stop(["capture", "flow", "motion", "render", "recorder", "router"])
    assert all(c == 0 for c in codes.values()), codes
