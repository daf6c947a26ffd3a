"""Zenoh session set-up shared by every service: the standard zenoh CLI flags -> ``zenoh.Config``.

Flags as in the zenoh-python examples: ``-m/--mode``, ``-e/--connect``,
``-l/--listen``, ``-c/--config``, ``--no-multicast-scouting``, ``--cfg KEY:VALUE``
(VALUE is JSON5, e.g. ``--cfg 'transport/shared_memory/enabled:false'``).
Pitfalls measured here (design/transport-facts.md): peers that only connect to a
router exchange no data unless they also listen, so a peer with ``-e`` and no
``-l`` listens on an ephemeral port (``tcp/127.0.0.1:0`` when every endpoint it
connects to is on loopback, else ``tcp/0.0.0.0:0``, so peers on other hosts can
reach it); never enable ``transport/unicast/lowlatency``. Without a config file the
connection to ``-e`` endpoints is retried from 100 ms, backing off to 1 s (zenoh's
default: 1 s to 4 s), so a service restarted together with the router resumes sooner.

Environment overrides (for containers and units; a CLI flag beats the variable,
the variable beats the config file): ``QUICK_STREAM_ZENOH_CONFIG`` (file),
``QUICK_STREAM_ZENOH_MODE``, ``QUICK_STREAM_ZENOH_CONNECT`` and
``QUICK_STREAM_ZENOH_LISTEN`` (comma-separated endpoints),
``QUICK_STREAM_ZENOH_TLS_DIR`` and ``QUICK_STREAM_ZENOH_TLS_NAME``.

TLS: ``--tls-dir DIR --tls-name NAME`` uses DIR/ca.pem and DIR/NAME.pem/.key
(as written by deploy/tls/make-certs.sh) with mutual authentication: the
certificate is shown when connecting and, in router mode, when accepting.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Mapping

import zenoh


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("-m", "--mode", choices=("peer", "client", "router"), help="session mode (default peer)")
    g.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    g.add_argument("-c", "--config", metavar="FILE", help="zenoh JSON5 configuration file")
    g.add_argument("--no-multicast-scouting", action="store_true", help="disable multicast scouting")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="set a configuration key to a JSON5 value (repeatable)")
    g.add_argument("--tls-dir", default=None, metavar="DIR",
                   help="TLS with mutual authentication: DIR/ca.pem and DIR/<--tls-name>.pem/.key")
    g.add_argument("--tls-name", default=None, metavar="NAME",
                   help="this process's certificate name in --tls-dir (e.g. flow, router)")


ENV = "QUICK_STREAM_ZENOH_"
# Reconnection to the endpoints we connect to (zenoh's default starts at 1 s and backs off to 4 s):
# a service started while the router restarts is connected ~0.1 s after the router is back.
RECONNECT = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


def _env_list(environ: Mapping[str, str], name: str) -> list[str]:
    return [x.strip() for x in environ.get(ENV + name, "").split(",") if x.strip()]


def _loopback(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1")


def tls_settings(tls_dir: str, name: str, mode: str) -> dict[str, object]:
    """The zenoh ``transport/link/tls`` keys for certificates made by deploy/tls/make-certs.sh."""
    d = Path(tls_dir)
    for f in (d / "ca.pem", d / f"{name}.pem", d / f"{name}.key"):
        if not f.is_file():
            raise ValueError(f"--tls-dir {tls_dir} --tls-name {name}: missing {f}")
    out: dict[str, object] = {"root_ca_certificate": str(d / "ca.pem"), "enable_mtls": True,
                              "connect_certificate": str(d / f"{name}.pem"),
                              "connect_private_key": str(d / f"{name}.key")}
    if mode in ("router", "peer"):
        out.update(listen_certificate=str(d / f"{name}.pem"), listen_private_key=str(d / f"{name}.key"))
    return out


def config_from_args(args: argparse.Namespace, environ: Mapping[str, str] | None = None) -> zenoh.Config:
    """Build the session configuration; errors name the flag or key at fault (ValueError)."""
    env = os.environ if environ is None else environ
    config = args.config or env.get(ENV + "CONFIG") or None
    try:
        conf = zenoh.Config.from_file(config) if config else zenoh.Config()
    except (zenoh.ZError, OSError, ValueError) as e:
        raise ValueError(f"--config {config}: {e}") from None

    def put(key: str, value_json: str, flag: str) -> None:
        try:
            conf.insert_json5(key, value_json)
        except (zenoh.ZError, ValueError) as e:
            raise ValueError(f"{flag}: cannot set {key} to {value_json}: {e}") from None

    mode = args.mode or env.get(ENV + "MODE") or None
    connect = list(args.connect) or _env_list(env, "CONNECT")
    listen = list(args.listen) or _env_list(env, "LISTEN")
    if mode:
        put("mode", json.dumps(mode), "--mode")
    if connect:
        put("connect/endpoints", json.dumps(connect), "--connect")
    if listen:
        put("listen/endpoints", json.dumps(listen), "--listen")
    elif connect and (mode or "peer") == "peer" and not config:
        port0 = "tcp/127.0.0.1:0" if all(_loopback(e) for e in connect) else "tcp/0.0.0.0:0"
        put("listen/endpoints", json.dumps([port0]), "--connect")
    if connect and not config:
        put("connect/retry", json.dumps(RECONNECT), "--connect")
    if args.no_multicast_scouting:
        put("scouting/multicast/enabled", "false", "--no-multicast-scouting")
    tls_dir = getattr(args, "tls_dir", None) or env.get(ENV + "TLS_DIR")
    tls_name = getattr(args, "tls_name", None) or env.get(ENV + "TLS_NAME")
    if tls_dir or tls_name:
        if not (tls_dir and tls_name):
            raise ValueError("--tls-dir and --tls-name go together")
        for k, v in tls_settings(tls_dir, tls_name, mode or "peer").items():
            put(f"transport/link/tls/{k}", json.dumps(v), "--tls-dir")
    for item in args.cfg:
        k, sep, v = item.partition(":")
        if not sep or not k:
            raise ValueError(f"--cfg expects KEY:VALUE, got {item!r}")
        put(k, v, f"--cfg {item}")
    return conf
