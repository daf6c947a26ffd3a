"""The deployment files in deploy/ agree with the code and with each other.

No Docker engine or cluster runs where the tests run, so the compose files, the Kubernetes
manifests, the Dockerfile and the systemd units are checked statically:

* they parse (``yaml.safe_load_all``; the units line by line);
* every command they run exists in the CLI with those flags: ``quick_stream.services.X`` is parsed with that
  service's ``build_parser()``, ``quick_stream router`` with ``quick_stream.cli.build_parser()``,
  the eclipse/zenoh router's arguments with the zenohd flags used here; then the zenoh
  configuration is built from the parsed flags and the container's environment, as the
  service would at start-up (``transport.config_from_args``);
* every ``-c`` path is where a deploy/zenoh file is mounted (compose bind mounts, Kubernetes
  ConfigMap volumes, the Dockerfile's COPY, the units' install location), and it loads with
  ``zenoh.Config.from_file``; the ConfigMap holds the deploy/zenoh files byte for byte;
* ports and names agree: the router's listen port = the published compose port = the
  Kubernetes Service port and container port = the port clients and peers connect to, on the
  host name the compose service and the Kubernetes Service carry;
* outputs (MP4, MCAP) are written to volumes; TLS containers mount their own certificate
  (CN quick-<service>, a subject of the router's access control) and are clients;
* one process per stream per stage: no two running containers of the same stage on one stream,
  Kubernetes Deployments with at most one replica and the Recreate strategy.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import re
import shlex
import tomllib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import pytest
import yaml
import zenoh

from quick_stream.cli import main as cli_main
from quick_stream.io.settings_file import load_settings_file
from quick_stream.io.stabilizer_flags import SETTINGS_ENV
from quick_stream.stream import keys
from quick_stream.stream.acl import common_name
from quick_stream.stream.transport import config_from_args

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
ZENOH_DIR = DEPLOY / "zenoh"
ZENOH_FILES = sorted(p.name for p in ZENOH_DIR.glob("*.json5"))
K8S_FILES = sorted((DEPLOY / "k8s").glob("*.yaml"))
COMPOSE = DEPLOY / "compose.yaml"
COMPOSE_TLS = DEPLOY / "compose.tls.yaml"
UNITS = DEPLOY / "systemd"
SERVICES = sorted(p.stem for p in (ROOT / "services").glob("*.py") if p.stem != "__init__")
CONFIG_DIR = "/etc/quick-stream/zenoh"  # where every deployment puts the deploy/zenoh files
SETTINGS = DEPLOY / "settings.toml"  # the stabilizer settings every deployment's stages read
CONFIGMAP_DIRS = {"quick-stream-zenoh": ZENOH_DIR, "quick-stream-settings": DEPLOY}  # what each ConfigMap holds
ROUTER_HOST = "quick-router"  # the name client.json5 / peer.json5 / client-tls.json5 dial
OUR_IMAGE = "quick-stream"
ZENOHD_IMAGE = "eclipse/zenoh"


# ---------------------------------------------------------------- zenoh configurations

def zconf(name: str) -> zenoh.Config:
    return zenoh.Config.from_file(str(ZENOH_DIR / name))


def zget(conf: zenoh.Config, key: str):
    try:
        return json.loads(conf.get_json(key))
    except zenoh.ZError:
        return None


def endpoint_parts(endpoint: str) -> tuple[str, str, int]:
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    return proto, host.strip("[]"), int(port)


def router_endpoint(config_name: str) -> tuple[str, int]:
    """(protocol, port) the router configuration listens on."""
    conf = zconf(config_name)
    assert zget(conf, "mode") == "router", config_name
    (endpoint,) = zget(conf, "listen/endpoints")
    proto, host, port = endpoint_parts(endpoint)
    assert host == "0.0.0.0", f"{config_name}: the router must listen on every interface, not {host}"
    return proto, port


ROUTER_PORT = router_endpoint("router.json5")[1]


def test_zenoh_configs_agree_on_the_router_port():
    assert ROUTER_PORT == 7447
    assert router_endpoint("router.json5") == ("tcp", ROUTER_PORT)
    assert router_endpoint("router-tls.json5") == ("tls", ROUTER_PORT)
    for name, proto in (("client.json5", "tcp"), ("peer.json5", "tcp"), ("client-tls.json5", "tls")):
        conf = zconf(name)
        assert [endpoint_parts(e) for e in zget(conf, "connect/endpoints")] == [(proto, ROUTER_HOST, ROUTER_PORT)], name
    # a peer must listen (else it receives nothing), on an ephemeral port of every interface
    assert [endpoint_parts(e) for e in zget(zconf("peer.json5"), "listen/endpoints")] == [("tcp", "0.0.0.0", 0)]
    assert zget(zconf("client.json5"), "mode") == "client"
    assert zget(zconf("client-tls.json5"), "mode") == "client"


def tls_paths(conf: zenoh.Config) -> dict[str, str]:
    tls = zget(conf, "transport/link/tls") or {}
    return {k: v for k, v in tls.items() if isinstance(v, str) and v.startswith("/")}


def acl_common_names() -> set[str]:
    subjects = zget(zconf("router-tls.json5"), "access_control/subjects")
    policies = zget(zconf("router-tls.json5"), "access_control/policies")
    with_policy = {s for p in policies for s in p["subjects"]}
    return {cn for s in subjects if s["id"] in with_policy for cn in s.get("cert_common_names", [])}


# ---------------------------------------------------------------- the router's access control

def test_router_tls_is_the_generated_access_control():
    """router-tls.json5 is `quick-stream acl --streams cam0` (regenerated, never edited by hand)."""
    from quick_stream.stream.acl import router_config_text

    assert (ZENOH_DIR / "router-tls.json5").read_text() == router_config_text(["cam0"]), \
        "regenerate: quick-stream acl --streams cam0 --output deploy/zenoh/router-tls.json5"


class Acl:
    """Decides like zenoh's access control with default deny: a message is allowed when a rule of one
    of the subject's policies has its flow and message type and a key expression including its key."""

    def __init__(self, conf: dict) -> None:
        assert conf["enabled"] and conf["default_permission"] == "deny"
        rules = {r["id"]: r for r in conf["rules"]}
        assert len(rules) == len(conf["rules"]), "rule ids must be unique"
        assert all(r["permission"] == "allow" for r in conf["rules"])
        self.by_cn: dict[str, list[dict]] = {}
        subjects = {x["id"]: x for x in conf["subjects"]}
        for pol in conf["policies"]:
            for sid in pol["subjects"]:
                for cn in subjects[sid]["cert_common_names"]:
                    self.by_cn.setdefault(cn, []).extend(rules[r] for r in pol["rules"])

    def allows(self, cn: str, flow: str, message: str, key: str) -> bool:
        return any(flow in r["flows"] and message in r["messages"]
                   and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in r["key_exprs"])
                   for r in self.by_cn.get(cn, []))


def test_access_control_gives_each_certificate_what_its_service_needs_and_no_more():
    from quick_stream.stream.acl import access_control

    acl = Acl(access_control(["cam0", "cam1"]))
    assert Acl(zget(zconf("router-tls.json5"), "access_control")).by_cn.keys() == \
        {common_name(s, "cam0") for s in SERVICES} | {"quick-recorder", "quick-monitor"}
    publishes = {"capture": {"frame"}, "flow": {"flow"}, "motion": {"motion", "correction"},
                 "render": {"stabilized"}, "recorder": set()}
    stages = ("frame", "flow", "motion", "correction", "stabilized")
    for svc in SERVICES:
        cn = common_name(svc, "cam0")
        for stage in stages:  # publishes its own stages of its own stream; reads its stream
            assert acl.allows(cn, "ingress", "put", keys.key("cam0", stage)) == (stage in publishes[svc]), (cn, stage)
            assert not acl.allows(cn, "ingress", "put", keys.key("cam1", stage)), (cn, stage)
            assert acl.allows(cn, "egress", "put", keys.key("cam0", stage))
            assert not acl.allows(cn, "egress", "put", keys.key("cam1", stage))
        assert acl.allows(cn, "ingress", "declare_subscriber", keys.stream_keys("cam0"))
        assert not acl.allows(cn, "ingress", "declare_subscriber", keys.stream_keys("cam1"))
        assert acl.allows(cn, "ingress", "put", keys.key("cam0", "stats"))
        for other in SERVICES:  # its own liveliness token and cursor queryable, nobody else's
            own = other == svc
            assert acl.allows(cn, "ingress", "liveliness_token", keys.health_key("cam0", other)) == own, (cn, other)
            assert not acl.allows(cn, "ingress", "liveliness_token", keys.health_key("cam1", other))
            assert acl.allows(cn, "egress", "liveliness_token", keys.health_key("cam0", other))  # sees who is up
            serves = own and svc != "capture"  # capture asks the cursor, answers none
            for message in ("declare_queryable", "reply"):
                assert acl.allows(cn, "ingress", message, keys.cursor_key("cam0", other)) == serves, (cn, other)
                assert not acl.allows(cn, "ingress", message, keys.cursor_key("cam1", other))
        assert acl.allows(cn, "ingress", "query", keys.cursor_key("cam0")) == (svc != "recorder")
        # history caches (every lossless key): served by the stage's publisher, which alone sends their
        # heartbeats; read by its consumers (to take over and to recover what their link dropped)
        for stage, (server, readers) in {"frame": ("capture", {"flow", "render", "recorder"}),
                                         "flow": ("flow", {"motion", "recorder"}),
                                         "motion": ("motion", {"recorder"}),
                                         "correction": ("motion", {"render", "recorder"})}.items():
            adv = f"{keys.key('cam0', stage)}/@adv/pub/z/1/_"
            assert acl.allows(cn, "ingress", "declare_queryable", adv) == (svc == server), (cn, stage)
            assert acl.allows(cn, "ingress", "reply", keys.key("cam0", stage)) == (svc == server), (cn, stage)
            assert acl.allows(cn, "ingress", "put", adv) == (svc == server), (cn, stage)  # the heartbeat
            assert acl.allows(cn, "egress", "put", adv) == (svc in readers), (cn, stage)  # heard by its readers
            assert acl.allows(cn, "ingress", "query", adv) == (svc in readers), (cn, stage)
            assert not acl.allows(cn, "ingress", "query", f"{keys.key('cam1', stage)}/@adv/pub/z/1/_")
    # the monitor watches every stream: subscribes, receives, sees tokens; declares and publishes nothing
    for stream in ("cam0", "cam1"):
        assert acl.allows("quick-monitor", "egress", "put", keys.key(stream, "frame"))
        assert acl.allows("quick-monitor", "egress", "liveliness_token", keys.health_key(stream, "flow"))
        assert acl.allows("quick-monitor", "ingress", "declare_subscriber", keys.stream_keys(stream))
        for message, key in (("put", keys.key(stream, "frame")), ("put", keys.key(stream, "stats")),
                             ("liveliness_token", keys.health_key(stream, "monitor")),
                             ("declare_queryable", keys.cursor_key(stream, "flow")), ("query", keys.cursor_key(stream)),
                             ("query", f"{keys.key(stream, 'frame')}/@adv/pub/z/1/_")):
            assert not acl.allows("quick-monitor", "ingress", message, key), (message, key)
    # the recorder of every stream: reads all, answers the recorder's cursor and holds its token, publishes no data
    assert acl.allows("quick-recorder", "ingress", "declare_subscriber", f"{keys.PREFIX}/*/*")
    assert acl.allows("quick-recorder", "ingress", "declare_queryable", keys.cursor_key("*", "recorder"))
    assert not acl.allows("quick-recorder", "ingress", "declare_queryable", keys.cursor_key("*", "flow"))
    assert acl.allows("quick-recorder", "ingress", "liveliness_token", keys.health_key("cam1", "recorder"))
    assert acl.allows("quick-recorder", "ingress", "query", f"{keys.key('cam1', 'flow')}/@adv/pub/z/1/_")
    assert not acl.allows("quick-recorder", "ingress", "liveliness_token", keys.health_key("cam1", "flow"))
    assert not acl.allows("quick-recorder", "ingress", "put", keys.key("cam0", "frame"))


# ---------------------------------------------------------------- containers, as deployed

@dataclass
class Mount:
    source: Path | None  # local file or folder behind it (None: a volume, the USB bus, ...)
    read_only: bool
    configmap: dict[str, str] | None = None  # ConfigMap data (key -> text) behind it


@dataclass
class Container:
    where: str  # e.g. "compose.yaml:flow"
    name: str
    image: str
    argv: list[str]  # after the entrypoint: module + flags (ours), zenohd flags (router image)
    env: dict[str, str] = field(default_factory=dict)
    mounts: dict[str, Mount] = field(default_factory=dict)  # target path -> mount
    running: bool = True  # started by default (not a compose profile, replicas > 0)

    @property
    def ours(self) -> bool:
        return self.image.split(":")[0] == OUR_IMAGE

    def local_file(self, path: str) -> Path | None:
        """The repository file a path inside the container is, through its mounts (or the image)."""
        p = PurePosixPath(path)
        for target in sorted(self.mounts, key=len, reverse=True):
            t = PurePosixPath(target)
            if p == t or t in p.parents:
                m = self.mounts[target]
                rel = p.relative_to(t)
                if m.configmap is not None:
                    text = m.configmap.get(str(rel))
                    if text is None:
                        return None
                    # the ConfigMap's data is a deploy/ file, byte for byte (test_configmaps_are_the_deploy_files)
                    return m.source / str(rel)
                return None if m.source is None else m.source.joinpath(rel)
        if self.ours and p.parent == PurePosixPath(CONFIG_DIR):  # baked in by the Dockerfile's COPY
            return ZENOH_DIR / p.name
        return None

    def writable_mount(self, path: str) -> bool:
        p = PurePosixPath(path)
        return any(PurePosixPath(t) in p.parents and not m.read_only for t, m in self.mounts.items())


_VAR = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}|\$([A-Za-z_][A-Za-z0-9_]*)")


def interpolate(value, env: dict[str, str]):
    """Compose variable interpolation (``${VAR:-default}`` and friends) with ``env`` as the shell."""
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if not isinstance(value, str):
        return value

    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name = m.group(1) or m.group(4)
        op, default = m.group(2), m.group(3)
        have = env.get(name)
        if op in (":-", "-"):
            return have if have or (op == "-" and have is not None) else default
        if have is None:
            raise AssertionError(f"${{{name}}} has no default: the file does not run as it is")
        return have

    return _VAR.sub(sub, value)


def compose_env(service: dict) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.partition("=")[::2] if "=" in item else (item, None) for item in env)
    return {k: str(v) for k, v in env.items() if v is not None}  # no value: passed through when set


def compose_volume(entry, named: set[str]) -> tuple[str, Mount]:
    if isinstance(entry, dict):
        source, target, ro = entry.get("source"), entry["target"], bool(entry.get("read_only"))
        kind = entry.get("type", "volume")
    else:
        parts = entry.split(":")
        source, target = parts[0], parts[1]
        ro = len(parts) > 2 and "ro" in parts[2].split(",")
        kind = "volume" if source in named else "bind"
    if kind == "bind":
        assert source.startswith((".", "/", "~")), f"{entry}: a bind mount needs a path (or declare the volume)"
        return target, Mount(None if source.startswith("/dev/") else (DEPLOY / source).resolve(), ro)
    assert source in named, f"{entry}: named volume {source} is not declared under volumes:"
    return target, Mount(None, ro)


def merge_compose(base: dict, override: dict) -> dict:
    """docker compose -f base -f override, for the keys these files use."""
    out = {k: dict(v) for k, v in base["services"].items()}
    extra = set(override["services"]) - set(out)
    assert not extra, f"the override names services the base file does not have: {extra}"
    for name, svc in override["services"].items():
        merged = out[name]
        for key, value in svc.items():
            if key == "volumes":  # merged by target (of the interpolated entry: ${VAR:-x} holds a colon)
                def target(v):
                    return v["target"] if isinstance(v, dict) else interpolate(v, {}).split(":")[1]
                vols = {target(v): v for v in merged.get("volumes", [])}
                vols.update({target(v): v for v in value})
                merged["volumes"] = list(vols.values())
            elif key == "environment":
                merged["environment"] = {**compose_env(merged), **compose_env(svc)}
            else:
                merged[key] = value
    return {**base, "services": out}


def compose_containers(doc: dict, label: str) -> list[Container]:
    doc = interpolate(doc, {})
    named = set(doc.get("volumes") or {})
    out = []
    for name, svc in doc["services"].items():
        assert "image" in svc, f"{label}:{name}: no image"
        command = svc.get("command")
        assert isinstance(command, list), f"{label}:{name}: command must be a list (exec form)"
        mounts = dict(compose_volume(v, named) for v in svc.get("volumes", []))
        for dep in svc.get("depends_on") or []:
            assert dep in doc["services"], f"{label}:{name}: depends on unknown service {dep}"
        out.append(Container(f"{label}:{name}", name, svc["image"], [str(a) for a in command],
                             compose_env(svc), mounts, running=not svc.get("profiles")))
    return out


def load_yaml(path: Path) -> list[dict]:
    docs = [d for d in yaml.safe_load_all(path.read_text()) if d is not None]
    assert docs, f"{path} is empty"
    return docs


COMPOSE_DOC = load_yaml(COMPOSE)[0]
COMPOSE_TLS_DOC = load_yaml(COMPOSE_TLS)[0] if COMPOSE_TLS.exists() else None
K8S_DOCS = [(p.name, d) for p in K8S_FILES for d in load_yaml(p)]


def k8s_objects(kind: str) -> dict[str, dict]:
    return {d["metadata"]["name"]: d for _, d in K8S_DOCS if d["kind"] == kind}


def k8s_expand(arg: str, env: dict[str, str]) -> str:
    """Kubernetes' $(VAR) expansion of args from the container's env (unknown ones stay)."""
    return re.sub(r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)", lambda m: env.get(m.group(1), m.group(0)), arg)


def k8s_containers() -> list[Container]:
    configmaps = {n: d.get("data", {}) for n, d in k8s_objects("ConfigMap").items()}
    claims = set(k8s_objects("PersistentVolumeClaim"))
    out = []
    for fname, d in K8S_DOCS:
        if d["kind"] != "Deployment":
            continue
        spec = d["spec"]
        pod = spec["template"]["spec"]
        volumes = {v["name"]: v for v in pod.get("volumes", [])}
        for c in pod["containers"]:
            where = f"k8s/{fname}:{d['metadata']['name']}/{c['name']}"
            image = c["image"]
            if image.split(":")[0] == OUR_IMAGE:
                assert "command" not in c, f"{where}: keep the image's entrypoint (python -m); put the module in args"
            argv = [*c.get("command", []), *c.get("args", [])]
            env = {e["name"]: str(e.get("value", "")) for e in c.get("env", [])}
            argv = [k8s_expand(a, env) for a in argv]
            mounts = {}
            for vm in c.get("volumeMounts", []):
                assert vm["name"] in volumes, f"{where}: volumeMount {vm['name']} has no volume"
                vol = volumes[vm["name"]]
                ro = bool(vm.get("readOnly"))
                if "configMap" in vol:
                    cm = vol["configMap"]["name"]
                    assert cm in configmaps, f"{where}: ConfigMap {cm} is not in deploy/k8s"
                    data = configmaps[cm]
                    if vol["configMap"].get("items"):
                        data = {i["path"]: data[i["key"]] for i in vol["configMap"]["items"]}
                    assert "subPath" not in vm, f"{where}: mount the whole ConfigMap (a subPath never updates)"
                    assert cm in CONFIGMAP_DIRS, f"{where}: ConfigMap {cm} mirrors no deploy/ folder"
                    mounts[vm["mountPath"]] = Mount(CONFIGMAP_DIRS[cm], ro, data)
                    assert ro, f"{where}: mount the ConfigMap read-only"
                elif "persistentVolumeClaim" in vol:
                    claim = vol["persistentVolumeClaim"]["claimName"]
                    assert claim in claims, f"{where}: PersistentVolumeClaim {claim} is not in deploy/k8s"
                    mounts[vm["mountPath"]] = Mount(None, ro)
                else:
                    mounts[vm["mountPath"]] = Mount(None, ro)
            out.append(Container(where, d["metadata"]["name"], image, argv, env, mounts,
                                 running=spec.get("replicas", 1) > 0))
    return out


def deployments() -> dict[str, list[Container]]:
    out = {"compose.yaml": compose_containers(COMPOSE_DOC, "compose.yaml"), "k8s": k8s_containers()}
    if COMPOSE_TLS_DOC is not None:
        out["compose.yaml+compose.tls.yaml"] = compose_containers(merge_compose(COMPOSE_DOC, COMPOSE_TLS_DOC),
                                                                  "compose.tls.yaml")
    return out


DEPLOYMENTS = deployments()
ALL = [c for cs in DEPLOYMENTS.values() for c in cs]
OURS = [c for c in ALL if c.ours]
ROUTERS = [c for c in ALL if not c.ours]


# ---------------------------------------------------------------- parsing commands

def parse(parser: argparse.ArgumentParser, argv: list[str], where: str) -> argparse.Namespace:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_args(argv)
    except SystemExit:
        pytest.fail(f"{where}: {shlex.join(argv)}\n{err.getvalue()}")


def parse_ours(argv: list[str], where: str) -> tuple[str, argparse.Namespace]:
    """(service or "router", parsed flags) for `python -m <argv>`."""
    module = argv[0]
    if module in ("quick_stream", "quick_stream.cli"):
        from quick_stream.cli import build_parser

        args = parse(build_parser(), argv[1:], where)
        assert args.command == "router", f"{where}: only `quick_stream router` belongs in a deployment"
        return "router", args
    assert module.startswith("quick_stream.services."), f"{where}: {module} is not a service module"
    service = module.removeprefix("quick_stream.services.")
    assert service in SERVICES, f"{where}: no services/{service}.py"
    return service, parse(importlib.import_module(module).build_parser(), argv[1:], where)


def zenohd_parser() -> argparse.ArgumentParser:
    """The zenohd flags these files may use (zenohd's own names)."""
    p = argparse.ArgumentParser(prog="zenohd", exit_on_error=False)
    p.add_argument("-c", "--config", required=True)
    p.add_argument("-l", "--listen", action="append", default=[])
    p.add_argument("-e", "--connect", action="append", default=[])
    p.add_argument("--cfg", action="append", default=[])
    p.add_argument("--no-multicast-scouting", action="store_true")
    return p


def session_config(c: Container, args: argparse.Namespace) -> tuple[Path, zenoh.Config]:
    """The config file behind the container's -c (or QUICK_STREAM_ZENOH_CONFIG), and the session
    configuration the service builds from its flags and environment."""
    path = args.config or c.env.get("QUICK_STREAM_ZENOH_CONFIG")
    assert path, f"{c.where}: name the zenoh configuration (-c {CONFIG_DIR}/...)"
    local = c.local_file(path)
    assert local is not None and local.is_file(), f"{c.where}: {path} is not a mounted deploy/zenoh file"
    assert local.resolve().parent == ZENOH_DIR.resolve(), f"{c.where}: {path} -> {local}, not a deploy/zenoh file"
    zenoh.Config.from_file(str(local))
    local_args = argparse.Namespace(**{**vars(args), "config": str(local) if args.config else None})
    env = {**c.env}
    if "QUICK_STREAM_ZENOH_CONFIG" in env:
        env["QUICK_STREAM_ZENOH_CONFIG"] = str(local)
    try:
        conf = config_from_args(local_args, environ=env)
    except ValueError as e:
        pytest.fail(f"{c.where}: {e}")
    return local, conf


# ---------------------------------------------------------------- the tests

@pytest.mark.parametrize("c", OURS, ids=lambda c: c.where)
def test_service_commands_parse_and_configure(c: Container):
    service, args = parse_ours(c.argv, c.where)
    local, conf = session_config(c, args)
    if service == "router":
        assert zget(conf, "mode") == "router"
        return
    keys.check_stream(args.stream)
    mode = zget(conf, "mode")
    assert mode in ("client", "peer"), f"{c.where}: {local.name} makes a {mode}"
    for endpoint in zget(conf, "connect/endpoints"):
        proto, host, port = endpoint_parts(endpoint)
        assert (host, port) == (ROUTER_HOST, ROUTER_PORT), f"{c.where}: dials {endpoint}"
        assert proto == ("tls" if tls_paths(conf) else "tcp"), f"{c.where}: dials {endpoint} with {local.name}"
    for flag in ("output", "png"):
        path = getattr(args, flag, "")
        if path:
            assert c.writable_mount(path), f"{c.where}: --{flag} {path} is not on a writable volume"


@pytest.mark.parametrize("c", ROUTERS, ids=lambda c: c.where)
def test_router_containers(c: Container):
    assert c.image.split(":")[0] == ZENOHD_IMAGE, f"{c.where}: unknown image {c.image}"
    tag = c.image.partition(":")[2]
    assert re.fullmatch(r"1\.\d+\.\d+", tag), f"{c.where}: pin the zenoh router version (1.x.y), not {tag!r}"
    try:
        args = zenohd_parser().parse_args(c.argv)
    except (argparse.ArgumentError, SystemExit) as e:
        pytest.fail(f"{c.where}: zenohd {shlex.join(c.argv)}: {e}")
    assert not (args.listen or args.connect), f"{c.where}: keep endpoints in the config file"
    local = c.local_file(args.config)
    assert local is not None and local.is_file(), f"{c.where}: {args.config} is not a mounted deploy/zenoh file"
    assert local.name in ("router.json5", "router-tls.json5")
    assert router_endpoint(local.name)[1] == ROUTER_PORT
    assert c.name == ROUTER_HOST, f"{c.where}: name it {ROUTER_HOST}, the host the configs dial"


def test_one_router_version():
    tags = {c.image for c in ROUTERS}
    assert len(tags) == 1, f"one zenoh router image everywhere, not {tags}"


def test_compose_router_port_is_published():
    docs = {"compose.yaml": COMPOSE_DOC}
    if COMPOSE_TLS_DOC is not None:
        docs["compose.tls.yaml"] = merge_compose(COMPOSE_DOC, COMPOSE_TLS_DOC)
    for label, doc in docs.items():
        ports = doc["services"][ROUTER_HOST]["ports"]
        published = []
        for p in ports:
            if isinstance(p, dict):
                published.append((int(p["published"]), int(p["target"]), p.get("protocol", "tcp")))
            else:
                spec, _, proto = str(p).partition("/")
                host, _, target = spec.rpartition(":")
                published.append((int(host.rpartition(":")[2]), int(target), proto or "tcp"))
        assert (ROUTER_PORT, ROUTER_PORT, "tcp") in published, f"{label}: router ports {ports}"


def test_k8s_router_service_port():
    (svc,) = [s for n, s in k8s_objects("Service").items() if n == ROUTER_HOST]
    router = k8s_objects("Deployment")[ROUTER_HOST]
    tmpl = router["spec"]["template"]
    assert svc["spec"]["selector"].items() <= tmpl["metadata"]["labels"].items(), "the Service selects no router pod"
    (port,) = svc["spec"]["ports"]
    assert port["port"] == ROUTER_PORT and port.get("protocol", "TCP") == "TCP"
    container_ports = {p.get("name"): p["containerPort"]
                       for c in tmpl["spec"]["containers"] for p in c.get("ports", [])}
    target = port.get("targetPort", port["port"])
    assert container_ports.get(target, target) == ROUTER_PORT, f"targetPort {target} -> {container_ports}"
    assert ROUTER_PORT in container_ports.values()


def test_k8s_manifests_are_consistent():
    allowed = {"Deployment", "Service", "ConfigMap", "PersistentVolumeClaim"}
    for fname, d in K8S_DOCS:
        assert d["kind"] in allowed and d.get("apiVersion"), f"{fname}: {d.get('kind')}"
        assert "namespace" not in d["metadata"], f"{fname}: manifests stay namespace-less"
        if d["kind"] == "Deployment":
            spec = d["spec"]
            name = d["metadata"]["name"]
            assert spec["selector"]["matchLabels"].items() <= spec["template"]["metadata"]["labels"].items(), name
            assert spec.get("replicas", 1) <= 1, f"{name}: one process per stream per stage (add streams, not replicas)"
            assert spec.get("strategy", {}).get("type") == "Recreate", \
                f"{name}: a rolling update would run two processes of a stage at once"
    mounted_claims = {v["persistentVolumeClaim"]["claimName"] for _, d in K8S_DOCS if d["kind"] == "Deployment"
                      for v in d["spec"]["template"]["spec"].get("volumes", []) if "persistentVolumeClaim" in v}
    assert mounted_claims == set(k8s_objects("PersistentVolumeClaim")), "a claim nobody mounts, or one missing"


def test_configmaps_are_the_deploy_files():
    cms = k8s_objects("ConfigMap")
    assert sorted(cms) == sorted(CONFIGMAP_DIRS)
    zenoh_cm, settings_cm = cms["quick-stream-zenoh"], cms["quick-stream-settings"]
    assert sorted(zenoh_cm["data"]) == ZENOH_FILES
    for name in ZENOH_FILES:
        assert zenoh_cm["data"][name] == (ZENOH_DIR / name).read_text(), \
            f"deploy/k8s/configmap.yaml: {name} differs from deploy/zenoh/{name}"
    assert settings_cm["data"] == {SETTINGS.name: SETTINGS.read_text()}, \
        "deploy/k8s/configmap.yaml: quick-stream-settings differs from deploy/settings.toml"


STAGES = ("flow", "motion", "recorder", "render")  # the services that run with the stabilizer settings


@pytest.mark.parametrize("label", sorted(DEPLOYMENTS))
def test_every_stage_reads_the_one_settings_file(label: str):
    """flow, motion, render and the recorder of a deployment read deploy/settings.toml (mounted read-only),
    the same file, through --settings: one set of settings, the recording's record among them."""
    read = {}
    for c in DEPLOYMENTS[label]:
        if not c.ours:
            continue
        service, args = parse_ours(c.argv, c.where)
        if service not in STAGES:
            continue
        assert args.settings, f"{c.where}: give it the settings file (--settings)"
        local = c.local_file(args.settings)
        assert local is not None and local.resolve() == SETTINGS.resolve(), \
            f"{c.where}: --settings {args.settings} is {local}, not deploy/settings.toml"
        mount = max((t for t in c.mounts if PurePosixPath(t) == PurePosixPath(args.settings)
                     or PurePosixPath(t) in PurePosixPath(args.settings).parents), key=len)
        assert c.mounts[mount].read_only, f"{c.where}: mount {mount} read-only"
        read[(service, args.stream)] = args.settings
    assert {s for s, _ in read} == set(STAGES), f"{label}: {sorted(read)}"
    assert len(set(read.values())) == 1, f"{label}: one settings file for every stage, not {read}"


def test_the_deploy_settings_file_loads_and_the_unit_names_it():
    load_settings_file(SETTINGS)  # every key known, every value accepted
    unit = (UNITS / "quick-stream@.service").read_text()
    assert f"{SETTINGS_ENV}=/etc/quick-stream/settings.toml" in unit


def test_the_deploy_settings_file_is_the_defaults_as_settings_show_prints_them():
    """It says it is the defaults: every key, with the defaults' digest (a new setting or default shows)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["settings", "show"]) == 0
    assert SETTINGS.read_text() == out.getvalue(), \
        "deploy/settings.toml is not the defaults: quick-stream settings show --output deploy/settings.toml"


def test_each_stream_has_one_process_per_stage():
    for label, cs in DEPLOYMENTS.items():
        seen: dict[tuple[str, str], str] = {}
        for c in cs:
            if not (c.ours and c.running):
                continue
            service, args = parse_ours(c.argv, c.where)
            if service == "router":
                continue
            key = (service, args.stream)
            assert key not in seen, f"{label}: {c.where} and {seen[key]} both run {service} on {args.stream}"
            seen[key] = c.where
        streams = {s for _, s in seen}
        for stream in streams:
            assert {s for s, st in seen if st == stream} == set(SERVICES), \
                f"{label}: stream {stream} runs {sorted(s for s, st in seen if st == stream)}"


@pytest.mark.skipif(COMPOSE_TLS_DOC is None, reason="no compose.tls.yaml")
def test_compose_tls_mounts_each_service_its_own_certificate():
    names = acl_common_names()
    for c in DEPLOYMENTS["compose.yaml+compose.tls.yaml"]:
        if c.ours:
            service, args = parse_ours(c.argv, c.where)
            local, conf = session_config(c, args)
            assert zget(conf, "mode") == "client", f"{c.where}: peers bypass the router's access control"
            expect = {"root_ca_certificate": "ca.pem", "connect_certificate": f"{service}.pem",
                      "connect_private_key": f"{service}.key"}
            cn = common_name(service, args.stream)  # one service of one stream
            assert cn in names, f"{c.where}: CN {cn} has no access-control policy"
        else:
            (config,) = [c.argv[i + 1] for i, a in enumerate(c.argv) if a in ("-c", "--config")]
            local = c.local_file(config)
            conf = zenoh.Config.from_file(str(local))
            expect = {"root_ca_certificate": "ca.pem", "listen_certificate": "router.pem",
                      "listen_private_key": "router.key"}
        paths = tls_paths(conf)
        assert paths, f"{c.where}: {local.name} is not a TLS configuration"
        assert {k: v for k, v in paths.items() if k in expect}.keys() == expect.keys(), f"{c.where}: {paths}"
        for k, want in expect.items():
            src = c.local_file(paths[k])
            assert src is not None and src.name == want, f"{c.where}: {paths[k]} should be the host's {want}, is {src}"
            # from the party's own folder (make-certs.sh: STREAM/SERVICE/, router/)
            folder = [args.stream, service] if c.ours else ["router"]
            assert list(src.parent.parts[-len(folder):]) == folder, f"{c.where}: {paths[k]} is {src}"
            assert c.mounts[paths[k]].read_only, f"{c.where}: mount {paths[k]} read-only"
        if c.ours:  # and nobody else's key
            others = {f"{s}.key" for s in SERVICES if s != service} | {"router.key", "ca.key"}
            assert not {m.source.name for m in c.mounts.values() if m.source} & others, c.where


# ---------------------------------------------------------------- Dockerfile

def dockerfile() -> list[tuple[str, str]]:
    text = (DEPLOY / "Dockerfile").read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            instr, _, rest = line.partition(" ")
            out.append((instr.upper(), rest.strip()))
    return out


def test_dockerfile():
    instrs = dockerfile()
    assert instrs[0] == ("FROM", "python:3.11-slim")
    assert json.loads(dict(instrs)["ENTRYPOINT"]) == ["python", "-m"]
    copies = [r.split() for i, r in instrs if i == "COPY"]
    for *sources, _dest in copies:
        for s in sources:
            assert (ROOT / s).exists(), f"Dockerfile: COPY {s}: no such path in the build context (repo root)"
    assert ["deploy/zenoh", CONFIG_DIR] in copies, "the zenoh configs are baked in at " + CONFIG_DIR
    copied = {PurePosixPath(s).parts[0] for *sources, _ in copies for s in sources}
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    setup = pyproject["tool"]["setuptools"]
    folders = {setup["package-dir"].get(p, p.replace(".", "/")).split("/")[0] for p in setup["packages"]}
    assert folders == {"quick_stream", "services"}, folders
    assert folders <= copied and "pyproject.toml" in copied and pyproject["project"]["readme"] in copied
    assert any(i == "RUN" and "pip install" in r for i, r in instrs)
    users = [r for i, r in instrs if i == "USER"]
    assert users and users[-1] not in ("root", "0"), "the services run as a normal user"
    args = dict(r.partition("=")[::2] for i, r in instrs if i == "ARG")
    assert "EXTRAS" in args
    # the camera image's extra exists; the image's uid is the one the manifests run as
    builds = [s["build"] for s in COMPOSE_DOC["services"].values() if "build" in s]
    assert builds, "compose builds the image"
    for b in builds:
        assert (DEPLOY / b["context"] / b["dockerfile"]).resolve() == (DEPLOY / "Dockerfile").resolve()
        for k, v in (b.get("args") or {}).items():
            assert k in args, f"build arg {k} is not an ARG"
            if k == "EXTRAS":
                assert v in pyproject["project"]["optional-dependencies"], v
    for _, d in K8S_DOCS:
        if d["kind"] == "Deployment":
            sec = d["spec"]["template"]["spec"].get("securityContext", {})
            if "runAsUser" in sec:
                assert str(sec["runAsUser"]) == args["UID"], d["metadata"]["name"]
            if "fsGroup" in sec:
                assert str(sec["fsGroup"]) == args["GID"], d["metadata"]["name"]


# ---------------------------------------------------------------- systemd

def unit(path: Path) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    section = None
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        assert section, f"{path.name}: {line} outside a section"
        k, sep, v = line.partition("=")
        assert sep, f"{path.name}: not KEY=VALUE: {line}"
        out.setdefault(f"{section}.{k.strip()}", []).append(v.strip())
    return out


def exec_argv(u: dict[str, list[str]], instance: str, env_file: dict[str, str]) -> list[str]:
    env = dict(e.partition("=")[::2] for e in u.get("Service.Environment", []))
    env.update(env_file)
    (line,) = u["Service.ExecStart"]
    out = []
    for word in shlex.split(line.replace("%i", instance)):
        if re.fullmatch(r"\$[A-Za-z_]\w*", word):  # $VAR: split on white space
            out += env.get(word[1:], "").split()
        else:
            out.append(re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], word))
    return out


def bare_host(argv: list[str], where: str) -> Container:
    assert argv[:2] == ["/opt/quick-stream/venv/bin/python", "-m"], f"{where}: {argv[:2]}"
    return Container(where, where, OUR_IMAGE, argv[2:])  # the install puts deploy/zenoh at CONFIG_DIR


def test_systemd_service_template():
    u = unit(UNITS / "quick-stream@.service")
    assert u["Service.Restart"] == ["on-failure"]
    assert u["Service.KillSignal"] == ["SIGTERM"]
    assert u["Service.TimeoutStopSec"] == ["10"]
    assert "-/etc/quick-stream/%i.env" in u["Service.EnvironmentFile"] or \
        "/etc/quick-stream/%i.env" in u["Service.EnvironmentFile"]
    assert u["Install.WantedBy"] == ["multi-user.target"]
    outputs = {"render": "--output /var/lib/quick-stream/cam1.mp4", "recorder": "--output /var/lib/quick-stream/cam1.mcap"}
    for service in SERVICES:
        env_file = {"STREAM": "cam1", "QS_ARGS": outputs.get(service, "")}  # as docs/deployment.md shows
        c = bare_host(exec_argv(u, service, env_file), f"quick-stream@{service}")
        got, args = parse_ours(c.argv, c.where)
        assert got == service and args.stream == "cam1"
        local, _ = session_config(c, args)
        assert local.name == "client.json5"


def test_systemd_router_unit():
    u = unit(UNITS / "quick-stream-router.service")
    assert u["Service.Restart"] == ["on-failure"] and u["Service.KillSignal"] == ["SIGTERM"]
    for config in (None, f"{CONFIG_DIR}/router-tls.json5"):
        c = bare_host(exec_argv(u, "", {"ROUTER_CONFIG": config} if config else {}), "quick-stream-router")
        got, args = parse_ours(c.argv, c.where)
        assert got == "router"
        local = c.local_file(args.config)
        assert local.is_file() and router_endpoint(local.name)[1] == ROUTER_PORT


def test_every_service_is_deployed_everywhere():
    for label, cs in DEPLOYMENTS.items():
        deployed = {parse_ours(c.argv, c.where)[0] for c in cs if c.ours}
        assert set(SERVICES) <= deployed, f"{label} lacks {set(SERVICES) - deployed}"
    assert ROUTERS, "a router"
