"""A zenoh session that subscribes or publishes for a while, run inside a network namespace by
tests/integration/test_netns.py. Prints one JSON line: {"opened": bool, "received": n, "sent": n, "error": str}
(a subscriber first prints {"subscribed": true} once its subscriber is declared).

    python tests/tools/netns_probe.py sub|pub|cache|history ENDPOINT KEY SECONDS[:COUNT] [TLS_DIR TLS_NAME]

``cache``: an advanced publisher with a 20-message history cache puts 20 messages, prints
{"published": 20}, then stays SECONDS; ``history``: an advanced subscriber that asks the
publishers' caches for their history counts what it gets in SECONDS. ``sub`` and ``history`` stop
early once COUNT samples arrived, and ``sub`` also when its stdin closes (the test closes it once
the publisher it listens to has finished: the end of the publication, not a clock).
"""
from __future__ import annotations

import json
import sys
import threading
import time

import zenoh
import zenoh.ext


def main(argv: list[str]) -> int:
    role, endpoint, key = argv[0], argv[1], argv[2]
    seconds_s, _, count_s = argv[3].partition(":")
    seconds, count = float(seconds_s), int(count_s) if count_s else None
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true")  # history caches need timestamps
    if len(argv) > 5:
        d, name = argv[4], argv[5]
        for k, v in {"root_ca_certificate": f"{d}/ca.pem", "connect_certificate": f"{d}/{name}.pem",
                     "connect_private_key": f"{d}/{name}.key", "enable_mtls": True}.items():
            conf.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    out = {"opened": False, "received": 0, "sent": 0, "error": ""}
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        out["error"] = str(e)[:300]
        print(json.dumps(out))
        return 0
    out["opened"] = True
    lock = threading.Lock()
    done = threading.Event()

    def on_sample(_sample: zenoh.Sample) -> None:
        with lock:
            out["received"] += 1
            if count is not None and out["received"] >= count:
                done.set()

    try:
        if role == "cache":
            pub = zenoh.ext.declare_advanced_publisher(session, key, cache=zenoh.ext.CacheConfig(20),
                                                       publisher_detection=True)
            for i in range(20):
                pub.put(f"cached {i}".encode())
                out["sent"] += 1
            print(json.dumps({"published": out["sent"]}), flush=True)
            time.sleep(seconds)
        elif role == "history":
            sub = zenoh.ext.declare_advanced_subscriber(
                session, key, on_sample, history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
            done.wait(seconds)
            sub.undeclare()
        elif role == "sub":
            sub = session.declare_subscriber(key, on_sample)
            threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
            print(json.dumps({"subscribed": True}), flush=True)  # the test starts publishing on this line
            done.wait(seconds)
            sub.undeclare()
        else:
            pub = session.declare_publisher(key)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pub.put(b"intruder")
                out["sent"] += 1
                time.sleep(0.05)
    finally:
        session.close()
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
