"""The pipeline's table (quick_stream/stream/topology.py) is the one place its shape is written: the
services publish what it says, the access control, the lossless keys, the capture's receivers and
pacing, ``up`` and the benchmark read it."""
from __future__ import annotations

import re

import pytest

from quick_stream.core.pacing import CREDIT_STAGES
from quick_stream.core.shedding import UPSTREAM
from quick_stream.stream import acl, keys, topology
from quick_stream.stream.capture import FRAME_RECEIVERS
from tests.tools import REPO


def test_every_key_has_one_publisher_and_every_read_key_one_too():
    published = [k for s in topology.PIPELINE for k in s.publishes]
    assert len(published) == len(set(published)) and set(published) <= set(keys.STAGES)
    for s in topology.PIPELINE:
        assert set(s.reads) <= set(published) | {"stats"}, s
        assert set(s.history) <= set(s.reads) and set(s.history) <= set(topology.LOSSLESS_KEYS), s
        assert s.cursor is None or s.cursor in s.publishes, s


def test_the_services_publish_their_rows_keys_and_never_choose_the_delivery():
    """A key made lossless in one place and not another was a bug: render published stabilized frames
    numbered, and the recorder subscribed to them plainly, so it never recovered one."""
    for s in topology.PIPELINE:
        text = (REPO / "services" / f"{s.name}.py").read_text()
        assert set(re.findall(r"rt\.publisher\(\"(\w+)\"", text)) == set(s.publishes), s.name
        assert "lossless=" not in text, f"services/{s.name}.py chooses a key's delivery: stream/topology.py does"


def test_what_reads_the_table():
    assert topology.LOSSLESS_KEYS == tuple(k for s in topology.PIPELINE for k in s.publishes)
    assert acl.SERVICES == topology.SERVICES and acl.LOSSLESS == topology.LOSSLESS_KEYS
    assert acl.CACHE == {s.name: s.publishes for s in topology.PIPELINE if s.publishes}
    assert acl.READS_HISTORY["recorder"] == topology.LOSSLESS_KEYS  # the recorder recovers every data key
    assert FRAME_RECEIVERS == set(topology.receivers("frame")) == {"flow", "render", "recorder"}
    assert set(topology.BY_NAME[topology.SOURCE].reads) == set(CREDIT_STAGES)  # the capture paces on them
    # what a shed-limited stage needs up is what the table says its key is computed through
    assert UPSTREAM == {k: topology.upstream(k) for k in CREDIT_STAGES}
    assert topology.START_ORDER[0] == topology.RECORDER and topology.START_ORDER[-1] == topology.SOURCE


def test_one_streams_command_lines_come_from_the_table():
    from quick_stream.stream.stream_specs import stream_specs

    specs = stream_specs(lambda s: ["-e", "E", "--stream", "cam1"], {"render": ["--output", "v.avi"]},
                         modules={"render": "tests.tools.slow_render"}, name=lambda s: f"{s}-cam1")
    assert [s.name for s in specs] == [f"{s}-cam1" for s in topology.START_ORDER]
    by = {s.name.split("-")[0]: s for s in specs}
    assert by["render"].argv == ["-m", "tests.tools.slow_render", "-e", "E", "--stream", "cam1", "--output", "v.avi"]
    # the capture waits for the others started with it (their liveliness tokens: service names) and may finish
    assert by["capture"].argv[-2:] == ["--wait-for", "recorder,flow,motion,render"] and by["capture"].may_finish
    assert not any(s.may_finish for s in specs[:-1])
    alone = stream_specs(lambda s: [], run=("capture", "flow"))
    assert [s.name for s in alone] == ["flow", "capture"] and alone[1].argv[-1] == "flow"
    with pytest.raises(ValueError, match="no such services"):
        stream_specs(lambda s: [], run=("capture", "viewer"))
