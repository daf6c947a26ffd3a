"""Zenoh session set-up shared by every service: the standard zenoh CLI flags -> ``zenoh.Config``.

Flags as in the zenoh-python examples: ``-m/--mode``, ``-e/--connect``,
``-l/--listen``, ``-c/--config``, ``--no-multicast-scouting``, ``--cfg KEY:VALUE``
(VALUE is JSON5, e.g. ``--cfg 'transport/shared_memory/enabled:false'``).
Pitfalls measured on these machines: peers that only connect to a
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
import re
from pathlib import Path
from typing import Any, Iterator, Mapping

import zenoh


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("-m", "--mode", choices=("peer", "client", "router"),
                   help="session mode (default: peer, or $QUICK_STREAM_ZENOH_MODE, or the -c file's)")
    g.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447; repeatable (default: none, or "
                        "$QUICK_STREAM_ZENOH_CONNECT, comma-separated)")
    g.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on; repeatable (default: none, or $QUICK_STREAM_ZENOH_LISTEN; "
                        "a peer with -e listens on a free port)")
    g.add_argument("-c", "--config", metavar="FILE",
                   help="zenoh JSON5 configuration file (default: none, or $QUICK_STREAM_ZENOH_CONFIG)")
    g.add_argument("--no-multicast-scouting", action="store_true",
                   help="disable multicast scouting (the default here: see --multicast-scouting)")
    g.add_argument("--multicast-scouting", action="store_true",
                   help="discover peers and routers by UDP multicast (off unless asked for, or set by the -c file: "
                   "separate deployments on one network would otherwise join)")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="set a configuration key to a JSON5 value, e.g. transport/shared_memory/enabled:false; "
                   "repeatable (default: none)")
    g.add_argument("--tls-dir", default=None, metavar="DIR",
                   help="TLS with mutual authentication: DIR/ca.pem and DIR/<--tls-name>.pem/.key (default: no TLS, "
                   "or $QUICK_STREAM_ZENOH_TLS_DIR)")
    g.add_argument("--tls-name", default=None, metavar="NAME",
                   help="this process's certificate name in --tls-dir, e.g. flow, router (default: none, or "
                   "$QUICK_STREAM_ZENOH_TLS_NAME)")


ENV = "QUICK_STREAM_ZENOH_"
# Reconnection to the endpoints we connect to (zenoh's default starts at 1 s and backs off to 4 s):
# a service started while the router restarts is connected ~0.1 s after the router is back.
RECONNECT = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}
CLIENT_CONNECT_TIMEOUT_MS = 30_000  # how long a client's session keeps trying to reach its router when it opens


def _env_list(environ: Mapping[str, str], name: str) -> list[str]:
    return [x.strip() for x in environ.get(ENV + name, "").split(",") if x.strip()]


def _loopback(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1")


MODES = ("peer", "client", "router")
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")  # locators of the form HOST:PORT


def check_endpoint(endpoint: str, listen: bool = False) -> str:
    """``endpoint`` if it is ``<protocol>/<address>`` with, for IP protocols, ``HOST:PORT`` (port 1-65535;
    0 too when listening: any free port); else ValueError. Zenoh itself takes ``tcp/nohost`` or a port
    out of range for a peer's connect endpoint and then retries it forever without a word."""
    locator = str(endpoint).split("#", 1)[0].split("?", 1)[0]
    proto, sep, addr = locator.partition("/")
    if not (sep and proto and addr):
        raise ValueError(f"endpoint {endpoint!r} is not <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    if proto.lower() not in IP_PROTOCOLS:
        return endpoint
    host, sep, port = addr.rpartition(":")
    if not sep or not host.strip("[]") or (":" in host and not (host.startswith("[") and host.endswith("]"))):
        raise ValueError(f"endpoint {endpoint!r}: expected {proto}/HOST:PORT (an IPv6 host in brackets)")
    low = 0 if listen else 1
    if not port.isdigit() or not low <= int(port) <= 65535:
        raise ValueError(f"endpoint {endpoint!r}: port must be an integer in [{low}, 65535], got {port!r}")
    return endpoint


def zenoh_message(e: BaseException) -> str:
    """The readable part of a zenoh error: the JSON5 parser's message and position, without
    the Rust source locations."""
    text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(e)).strip()
    where = ""
    m = re.search(r'msg: "((?:[^"\\]|\\.)*)", location: Some\(Location \{ line: (\d+), column: (\d+)', text)
    if m:
        text = m.group(1).replace("\\n", "\n").replace('\\"', '"')
        where = f" (line {m.group(2)}, column {m.group(3)})"
    m = re.search(r"-->\s*(\d+):(\d+).*?=\s*([^\n]+)", text, re.S)  # the JSON5 parser's own report
    if m:
        return f"line {m.group(1)}, column {m.group(2)}: {m.group(3).strip()}"
    return re.sub(r'^Str\("(.*)"\)$', r"\1", text) + where


def _endpoint_strings(value: Any) -> Iterator[str]:
    """Endpoint strings in a ``connect/endpoints`` or ``listen/endpoints`` value: a list, a per-mode
    map of lists, or items with ``locators``."""
    if isinstance(value, str):
        yield value
    elif isinstance(value, list):
        for v in value:
            yield from _endpoint_strings(v)
    elif isinstance(value, dict):
        yield from _endpoint_strings(value["locators"] if "locators" in value else list(value.values()))


def _check_endpoints(endpoints: list[str], listen: bool, where: str) -> None:
    for endpoint in endpoints:
        try:
            check_endpoint(endpoint, listen)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None


def check_config_endpoints(conf: zenoh.Config, where: str) -> None:
    """ValueError naming ``where`` (the file, flag or variable that set them) if an endpoint is malformed."""
    for key, listen in (("connect/endpoints", False), ("listen/endpoints", True)):
        _check_endpoints(list(_endpoint_strings(json.loads(conf.get_json(key)))), listen, f"{where}: {key}")


def load_config(path: str, where: str) -> zenoh.Config:
    """The zenoh config in JSON5 file ``path``; ValueError starting with ``where`` (the flag or
    variable that named it) when the file is missing, empty, not JSON5 or not a valid config."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{where}: {'not a regular file' if p.exists() else 'no such file'}")
    try:
        empty = not p.read_text(errors="replace").strip()
    except OSError as e:
        raise ValueError(f"{where}: cannot read: {e.strerror or e}") from None
    if empty:
        raise ValueError(f"{where}: the file is empty (expected a JSON5 object, e.g. {{ mode: \"peer\" }})")
    try:
        conf = zenoh.Config.from_file(path)
    except (zenoh.ZError, OSError, ValueError) as e:
        raise ValueError(f"{where}: {zenoh_message(e)}") from None
    check_config_endpoints(conf, where)
    return conf


MULTICAST_KEY = "scouting/multicast/enabled"


def _sets_multicast(conf: zenoh.Config) -> bool:
    """Whether a configuration loaded from a ``-c`` file sets multicast scouting itself: zenoh's own
    JSON5 parser read the file, and a setting the file leaves out reads back ``null`` (comments,
    strings and keys are the parser's business: a comment naming multicast sets nothing)."""
    return json.loads(conf.get_json(MULTICAST_KEY)) is not None


def _setting(flag_value: Any, environ: Mapping[str, str], name: str, flag: str) -> tuple[Any, str]:
    """(value, what set it): the flag's value if given, else the environment variable's."""
    if flag_value:
        return flag_value, flag
    return environ.get(ENV + name) or None, ENV + name


def tls_settings(tls_dir: str, name: str, mode: str) -> dict[str, object]:
    """The zenoh ``transport/link/tls`` keys for the folder deploy/tls/make-certs.sh writes for one
    party (ca.pem, NAME.pem, NAME.key); a folder holding any other private key is refused."""
    d = Path(tls_dir)
    if not d.is_dir():
        raise ValueError(f"--tls-dir {tls_dir}: no such directory")
    for f in (d / "ca.pem", d / f"{name}.pem", d / f"{name}.key"):
        if not f.is_file():
            per_stream = sorted(str(p) for p in d.glob(f"*/{name}") if p.is_dir())
            hint = (f" (make-certs.sh writes each party's files to {d / name})" if (d / name).is_dir() else
                    f" (make-certs.sh writes each service's files per stream: {', '.join(per_stream)})" if per_stream
                    else "")
            raise ValueError(f"--tls-dir {tls_dir} --tls-name {name}: missing {f}{hint}")
    others = sorted(p.name for p in d.glob("*.key") if p.name != f"{name}.key")
    if others:  # a process is given its own key only: a folder of every key hands each the others' identity
        raise ValueError(f"--tls-dir {tls_dir}: holds other private keys ({', '.join(others)}); give each process a "
                         f"folder with only its own key (make-certs.sh writes DIR/{name}/: ca.pem, {name}.pem, {name}.key)")
    out: dict[str, object] = {"root_ca_certificate": str(d / "ca.pem"), "enable_mtls": True,
                              "connect_certificate": str(d / f"{name}.pem"),
                              "connect_private_key": str(d / f"{name}.key")}
    if mode in ("router", "peer"):
        out.update(listen_certificate=str(d / f"{name}.pem"), listen_private_key=str(d / f"{name}.key"))
    return out


DATA_QUEUE_KEY = "transport/link/tx/queue/size/data"
ZENOH_DEFAULT_DATA_QUEUE = 2  # batches
DATA_QUEUE_BATCHES = 16  # zenoh's maximum


def config_from_args(args: argparse.Namespace, environ: Mapping[str, str] | None = None) -> zenoh.Config:
    """Build the session configuration; errors name the flag or key at fault (ValueError)."""
    env = os.environ if environ is None else environ
    config, config_from = _setting(args.config, env, "CONFIG", "--config")
    conf = load_config(config, f"{config_from}{' ' if args.config else '='}{config}") if config else zenoh.Config()
    sets_multicast = _sets_multicast(conf)  # read before anything below sets it

    def put(key: str, value_json: str, flag: str) -> None:
        try:
            conf.insert_json5(key, value_json)
        except (zenoh.ZError, ValueError) as e:
            raise ValueError(f"{flag}: cannot set {key} to {value_json}: {zenoh_message(e)}") from None

    mode, mode_from = _setting(args.mode, env, "MODE", "--mode")
    if mode and mode not in MODES:
        raise ValueError(f"{mode_from}: mode must be one of {', '.join(MODES)}, got {mode!r}")
    connect = list(args.connect) or _env_list(env, "CONNECT")
    listen = list(args.listen) or _env_list(env, "LISTEN")
    _check_endpoints(connect, False, "--connect" if args.connect else ENV + "CONNECT")
    _check_endpoints(listen, True, "--listen" if args.listen else ENV + "LISTEN")
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
        if (mode or "peer") == "client":
            # zenoh opens a client's session only once it reaches a router, and by default fails at once:
            # a client restarted while its router restarts (under TLS every service is a client) exited 2
            # and `up` stopped the run; it now waits for the router, as a peer does in the background
            put("connect/timeout_ms", json.dumps(CLIENT_CONNECT_TIMEOUT_MS), "--connect")
    # publishers with a history cache (a restarted service takes over, runtime.py) need timestamps
    put("timestamping/enabled", "true", "timestamping")
    # Puts drop for a congested link instead of waiting (runtime.py): a link's data queue of zenoh's
    # default 2 batches (128 KiB) does not hold one raw 320x240 frame, so on a busy link such a frame
    # could be dropped within the 50 ms a fragmented message may wait, and a receiver's first frame cannot
    # be recovered (seen in tests/integration/test_netns.py under TLS). 16 batches (1 MiB) per link, unless
    # a -c file sets its own.
    if json.loads(conf.get_json(DATA_QUEUE_KEY)) == ZENOH_DEFAULT_DATA_QUEUE:
        put(DATA_QUEUE_KEY, str(DATA_QUEUE_BATCHES), "transport")
    # Multicast scouting is off unless asked for (zenoh's default is on: two deployments on one host
    # or network would find each other and mix their streams); a -c file that sets it keeps its choice.
    if getattr(args, "multicast_scouting", False):
        if args.no_multicast_scouting:
            raise ValueError("--multicast-scouting and --no-multicast-scouting contradict each other")
        put(MULTICAST_KEY, "true", "--multicast-scouting")
    elif args.no_multicast_scouting or not (config and sets_multicast):
        put(MULTICAST_KEY, "false", "--no-multicast-scouting")
    tls_dir, dir_from = _setting(getattr(args, "tls_dir", None), env, "TLS_DIR", "--tls-dir")
    tls_name, name_from = _setting(getattr(args, "tls_name", None), env, "TLS_NAME", "--tls-name")
    if tls_dir or tls_name:
        if not (tls_dir and tls_name):
            given, missing = (dir_from, "--tls-name") if tls_dir else (name_from, "--tls-dir")
            raise ValueError(f"--tls-dir and --tls-name go together: {given} without {missing} "
                             f"(or {ENV}{missing[2:].upper().replace('-', '_')})")
        for k, v in tls_settings(tls_dir, tls_name, mode or "peer").items():
            put(f"transport/link/tls/{k}", json.dumps(v), "--tls-dir")
    for item in args.cfg:
        k, sep, v = item.partition(":")
        if not sep or not k:
            raise ValueError(f"--cfg expects KEY:VALUE, got {item!r}")
        put(k, v, f"--cfg {item}")
        check_config_endpoints(conf, f"--cfg {item}")
    return conf


def session_config(endpoint: str, mode: str = "client", tls_dir: str | None = None,
                   tls_name: str | None = None) -> zenoh.Config:
    """The configuration of a session of our own tools (``up``'s status board, the benches' monitors)
    to the router at ``endpoint``, built from the same flags as a service's (``-m -e
    --no-multicast-scouting [--tls-dir DIR --tls-name NAME]``), the environment ignored."""
    p = argparse.ArgumentParser(add_help=False)
    add_zenoh_args(p)
    argv = ["-m", mode, "-e", endpoint, "--no-multicast-scouting"]
    if tls_dir is not None:
        argv += ["--tls-dir", str(tls_dir), "--tls-name", str(tls_name)]
    return config_from_args(p.parse_args(argv), environ={})
