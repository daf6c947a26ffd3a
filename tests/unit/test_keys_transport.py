"""Key expressions and the zenoh flag set; a router and two peers exchange a wire message on loopback."""
import argparse
import json

import pytest

from quick_stream.stream import keys
from quick_stream.stream.transport import add_zenoh_args, config_from_args


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


def test_a_config_file_sets_multicast_only_by_its_setting(tmp_path):
    """Issue 30 row 7: the -c file is read by zenoh's JSON5 parser, not searched for a word: a comment at
    the end of a line or a string naming multicast leaves it off; the file's own setting, on or off,
    written any way JSON5 allows, is kept."""
    def multicast(text: str) -> bool:
        f = tmp_path / "z.json5"
        f.write_text(text)
        return json.loads(config_from_args(_args(["-c", str(f)]), {}).get_json("scouting/multicast/enabled"))

    assert multicast('{\n  mode: "peer", // multicast not wanted here\n}') is False
    assert multicast('{ mode: "peer", metadata: { note: "no multicast" } }') is False
    assert multicast('{ mode: "peer", scouting: { gossip: { enabled: true } } } // multicast: off') is False
    assert multicast("{ scouting: { 'multicast': { enabled: true, }, }, }") is True
    assert multicast('{ "scouting": { "multicast": { "enabled": false } } }') is False
    assert multicast('{ scouting: { multicast: { enabled: /* yes */ true } } }') is True
