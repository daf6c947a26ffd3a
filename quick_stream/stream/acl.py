"""The TLS router's access control, per stream: ``quick-stream acl --streams cam0,cam1``.

deploy/zenoh/router-tls.json5 is :func:`router_config_text` for ``cam0`` (the stream the deploy
files run; tests/unit/test_deploy_files.py checks the file is exactly that). A deployment of other or
more streams generates its own: zenoh's access control is read once, when the router starts.

Who is who is the client certificate's common name (deploy/tls/make-certs.sh ``--streams``):

* ``quick-<service>-<stream>`` (capture, flow, motion, render, recorder): one process of one
  stream. It may read its stream (subscribe, receive, ask who is alive), publish its own stages of
  it and its stats, hold its own liveliness token (``<stream>/health/<service>``) and nobody
  else's, answer the stream cursor as itself (``<stream>/cursor/<service>``; capture only asks),
  ask the cursor, read the history caches of the lossless stages it consumes (a restarted service
  takes over from them; every receiver recovers from them what its own link dropped) and serve the
  caches of the lossless stages it publishes, with their heartbeats. Nothing of another stream.
* ``quick-recorder``: a recorder of every stream (``recorder --all-streams``): reads every stream,
  holds the recorder's token and answers the recorder's cursor of every stream, publishes stats.
* ``quick-monitor``: watches every stream (``up``'s status board, the fault tool's monitor, tests/tools/faults.py):
  subscribes and receives, sees the liveliness tokens; declares, publishes and asks nothing.

Everything not allowed is denied (``default_permission: deny``). Rules apply to a message when one
of their key expressions includes the message's (zenoh does not match a rule that only overlaps:
a subscription on ``quick/@v1/*/*`` needs a rule on ``quick/@v1/**``, not one per stream).
"""
from __future__ import annotations

import json

from . import keys, topology

# all from the pipeline's table (stream/topology.py)
SERVICES = topology.SERVICES
PUBLISHES = {s.name: s.publishes for s in topology.PIPELINE}
# the caches each publisher keeps (every lossless key: docs/deployment.md, "Delivery guarantees per key"),
# whose heartbeats it sends on <key>/@adv/**
CACHE = {s.name: s.publishes for s in topology.PIPELINE if s.publishes}  # every data key is lossless
LOSSLESS = topology.LOSSLESS_KEYS
# the caches each service queries: to take over (a restarted one) and to recover what its link dropped
READS_HISTORY = {s.name: s.history for s in topology.PIPELINE if s.history}
ASKS_CURSOR = tuple(s.name for s in topology.PIPELINE if s.asks)  # a restarted service; capture before its end marker
SERVES_CURSOR = tuple(s.name for s in topology.PIPELINE if s.serves_cursor)
MONITOR = "monitor"
ALL_STREAMS_RECORDER = "recorder"
SUBSCRIBE = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]


def common_name(service: str, stream: str | None = None) -> str:
    """``quick-flow-cam0`` (a service of one stream), ``quick-monitor``, ``quick-recorder`` (every stream)."""
    return f"quick-{service}" + (f"-{keys.check_stream(stream)}" if stream is not None else "")


def _rule(rid: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict:
    return {"id": rid, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def _reading(scope: str, p: str) -> list[dict]:
    """Read ``p`` (a stream's prefix, or every stream's): receive, subscribe, see liveliness tokens."""
    health = f"{p}/health/*" if scope != "all" else f"{keys.PREFIX}/*/health/*"
    return [_rule(f"{scope} receive", "egress", ["put"], [f"{p}/**"]),
            _rule(f"{scope} subscribe", "ingress", SUBSCRIBE, [f"{p}/**"]),
            _rule(f"{scope} tokens seen", "egress", ["liveliness_token"], [health])]


def access_control(streams: list[str]) -> dict:
    """The ``access_control`` section for ``streams`` (see the module doc)."""
    streams = [keys.check_stream(s) for s in streams]
    if not streams or len(set(streams)) != len(streams):
        raise ValueError(f"streams must be one or more distinct stream ids, got {streams}")
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []

    def subject(sid: str, cn: str, rule_ids: list[str]) -> None:
        subjects.append({"id": sid, "cert_common_names": [cn]})
        policies.append({"subjects": [sid], "rules": rule_ids})

    # Declarations of subscribers and queryables reach every client, whatever their stream: a client's
    # publisher sends only where it knows a subscriber, and the monitor's, up's and an all-streams
    # recorder's subscriptions (quick/@v1/*/...) are no one stream's. Data, replies, queries and tokens
    # stay per stream.
    rules.append(_rule("declarations seen", "egress", [*SUBSCRIBE, "declare_queryable"], [f"{keys.PREFIX}/**"]))
    for s in streams:
        p = f"{keys.PREFIX}/{s}"
        rules += _reading(s, p)
        rules += [_rule(f"{s} stats", "ingress", ["put"], [f"{p}/stats"]),
                  _rule(f"{s} cursor ask", "ingress", ["query"], [f"{p}/cursor/*"]),
                  _rule(f"{s} cursor answers", "egress", ["reply"], [f"{p}/cursor/*"]),
                  _rule(f"{s} cursor queries", "egress", ["query"], [f"{p}/cursor/*"])]
        for stage in LOSSLESS:
            adv = [f"{p}/{stage}", f"{p}/{stage}/@adv/**"]
            rules += [_rule(f"{s} {stage} history ask", "ingress", ["query"], [f"{p}/{stage}/@adv/**"]),
                      # heartbeats too (puts on <key>/@adv/**: ** matches no @-chunk, so the stream's
                      # "receive" does not cover them)
                      _rule(f"{s} {stage} history seen", "egress", ["reply", "liveliness_token", "put"], adv),
                      _rule(f"{s} {stage} cache", "ingress", ["declare_queryable", "liveliness_token", "reply"], adv),
                      _rule(f"{s} {stage} cache queries", "egress", ["query"], [f"{p}/{stage}/@adv/**"])]
        for svc in SERVICES:
            rules.append(_rule(f"{s} {svc} token", "ingress", ["liveliness_token"], [keys.health_key(s, svc)]))
            if svc in SERVES_CURSOR:
                rules.append(_rule(f"{s} {svc} cursor", "ingress", ["declare_queryable", "reply"],
                                   [keys.cursor_key(s, svc)]))
            if PUBLISHES[svc]:  # its stages, and the heartbeats of its caches
                rules.append(_rule(f"{s} {svc} publish", "ingress", ["put"],
                                   [keys.key(s, st) for st in PUBLISHES[svc]]
                                   + [f"{keys.key(s, st)}/@adv/**" for st in CACHE.get(svc, ())]))
            granted = ["declarations seen", f"{s} receive", f"{s} subscribe", f"{s} tokens seen", f"{s} stats",
                       f"{s} {svc} token"]
            if svc in ASKS_CURSOR:
                granted += [f"{s} cursor ask", f"{s} cursor answers"]
            if svc in SERVES_CURSOR:
                granted += [f"{s} {svc} cursor", f"{s} cursor queries"]
            for stage in READS_HISTORY.get(svc, ()):
                granted += [f"{s} {stage} history ask", f"{s} {stage} history seen"]
            for stage in CACHE.get(svc, ()):
                granted += [f"{s} {stage} cache", f"{s} {stage} cache queries"]
            if PUBLISHES[svc]:
                granted.append(f"{s} {svc} publish")
            subject(f"{s} {svc}", common_name(svc, s), granted)
    # every stream: the recorder of all streams (--all-streams) and the monitor
    every = f"{keys.PREFIX}/*"
    rules += _reading("all", keys.PREFIX)
    rules += [_rule("all stats", "ingress", ["put"], [f"{every}/stats"]),
              _rule("all recorder token", "ingress", ["liveliness_token"], [f"{every}/health/{ALL_STREAMS_RECORDER}"]),
              _rule("all recorder cursor", "ingress", ["declare_queryable", "reply"],
                    [f"{every}/cursor/{ALL_STREAMS_RECORDER}"]),
              _rule("all cursor queries", "egress", ["query"], [f"{every}/cursor/*"]),
              _rule("all history ask", "ingress", ["query"], [f"{every}/{st}/@adv/**" for st in LOSSLESS]),
              _rule("all history seen", "egress", ["reply", "liveliness_token", "put"],
                    [k for st in LOSSLESS for k in (f"{every}/{st}", f"{every}/{st}/@adv/**")])]
    reading = ["declarations seen", "all receive", "all subscribe", "all tokens seen"]
    subject(f"all {ALL_STREAMS_RECORDER}", common_name(ALL_STREAMS_RECORDER),
            reading + ["all stats", "all recorder token", "all recorder cursor", "all cursor queries",
                       "all history ask", "all history seen"])
    subject(MONITOR, common_name(MONITOR), reading)
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


HEADER = """\
// quick-stream router with TLS, mutual authentication and access control, for stream(s) {streams}.
// Generated by `quick-stream acl --streams {streams}` (quick_stream/stream/acl.py): for other or more
// streams generate your own rather than editing this one (the router reads it once, at start).
// Only clients with a certificate from the deployment's CA get in (enable_mtls); what each may do
// is decided by its certificate's common name (deploy/tls/make-certs.sh --streams):
//   quick-<service>-<stream>  one service of one stream: reads that stream, publishes its own
//                             stages of it (capture: frame; flow: flow; motion: motion, correction;
//                             render: stabilized; recorder: nothing) and its stats, holds its own
//                             liveliness token and answers the stream cursor as itself only, reads
//                             the history caches of its inputs (to take over, and to recover what
//                             its link dropped), serves the caches of its lossless outputs and
//                             sends their heartbeats
//   quick-recorder            a recorder of every stream (recorder --all-streams)
//   quick-monitor             watches every stream: subscribes and sees liveliness tokens, no more
// Anything not allowed is denied. Services must be clients of this router (client-tls.json5):
// peers would talk to each other directly, around the router's access control.
"""


def router_config_text(streams: list[str]) -> str:
    """The whole router-tls.json5 for ``streams``: TLS listener on 7447 and :func:`access_control`."""
    acl = access_control(streams)

    def obj(x: dict) -> str:  # JSON5: bare keys, one object per line
        return "{ " + ", ".join(f"{k}: {json.dumps(v)}" for k, v in x.items()) + " }"

    def items(name: str) -> str:
        return "\n".join(f"      {obj(x)}," for x in acl[name])

    return (HEADER.format(streams=",".join(streams)) + "{\n"
            '  mode: "router",\n'
            '  listen: { endpoints: ["tls/0.0.0.0:7447"] },\n'
            "  scouting: { multicast: { enabled: false } },\n"
            "  transport: {\n    link: {\n"
            "      // each link's data queue holds 1 MiB (zenoh's default, 2 batches, does not hold one raw frame)\n"
            "      tx: { queue: { size: { data: 16 } } },\n"
            "      tls: {\n"
            '        root_ca_certificate: "/etc/quick-stream/tls/ca.pem",\n'
            '        listen_certificate: "/etc/quick-stream/tls/router.pem",\n'
            '        listen_private_key: "/etc/quick-stream/tls/router.key",\n'
            "        enable_mtls: true,\n"
            "      },\n    },\n  },\n"
            "  access_control: {\n    enabled: true,\n    default_permission: \"deny\",\n"
            f"    rules: [\n{items('rules')}\n    ],\n"
            f"    subjects: [\n{items('subjects')}\n    ],\n"
            f"    policies: [\n{items('policies')}\n    ],\n"
            "  },\n}\n")
