"""Tests of the msgpack wire format: round trips, every rejection case, and a fuzz test."""
from __future__ import annotations

import math
from dataclasses import replace

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from quick_stream.core.frame import Intrinsics, RGBDFrame
from quick_stream.core.motion import MotionEstimate, invalid_motion
from quick_stream.core.path.planner import Correction
from quick_stream.core.release_tags import Tag
from quick_stream.core.sceneflow import SceneFlowResult
from quick_stream.stream.wire import (
    FORMAT_VERSION,
    Decoded,
    EndOfStream,
    StabilizedImage,
    Stats,
    WireError,
    decode,
    dequantize_depth,
    encode,
    encode_correction,
    encode_end,
    encode_flow,
    encode_frame,
    encode_motion,
    encode_stabilized,
    encode_stats,
    quantize_depth,
)

K = Intrinsics(50.0, 51.0, 15.5, 11.5, 32, 24)


def make_frame(w: int = 32, h: int = 24, seed: int = 0, pose: bool = True) -> RGBDFrame:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    color = np.stack([xx * 255 // w, yy * 255 // h, (xx + yy) % 256], -1).astype(np.uint8)
    depth = rng.uniform(0.3, 5.0, (h, w)).astype(np.float32)
    depth[0, 0] = 0.0
    k = Intrinsics(50.0, 51.0, (w - 1) / 2, (h - 1) / 2, w, h)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    return RGBDFrame(color, depth, k, 1_700_000_000_123_456_789, 7, T if pose else None, "synthetic")


def make_flow(n: int = 50) -> SceneFlowResult:
    rng = np.random.default_rng(1)
    return SceneFlowResult(
        3, 4, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) * 0.01, rng.uniform(size=n),
        rng.uniform(0, 32, (n, 2)), rng.uniform(0, 32, (n, 2)), K, K.scaled(0.5),
        {"depth": 12, "fb": 3}, "",
    )


def make_motion() -> MotionEstimate:
    rng = np.random.default_rng(2)
    M = np.eye(4)
    M[:3, 3] = rng.normal(size=3)
    return MotionEstimate(9, 10, "sim3", "exact", M, rng.normal(size=7), True, "", 812, 0.93,
                          0.41, rng.normal(size=7))


def make_correction() -> Correction:
    M = np.eye(4)
    M[:3, 3] = [0.01, 0.02, -0.03]
    return Correction(11, M, 2, True, True, "")


def small_messages() -> list[bytes]:
    f = make_frame(8, 6)
    return [
        encode_frame(f, "cam0", color="raw", depth="raw"),
        encode_frame(f, "cam0", color="jpeg", depth="zstd"),
        encode_flow(make_flow(4), "cam0"),
        encode_motion(make_motion(), "cam0"),
        encode_correction(replace(make_correction(), zoom=1.1), "cam0"),
        encode_stabilized(StabilizedImage(5, 99, f.color, 1.2, ["late"]), "cam0", color="raw"),
        encode_stats(Stats("flow", {"fps": 29.9, "drops": 0, "state": "ok"}), "cam0", 3),
    ]


def raw(data: bytes) -> dict:
    return msgpack.unpackb(data, raw=False)


def repack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def rejects(data: bytes, *words: str, **kw) -> WireError:
    with pytest.raises(WireError) as ei:
        decode(data, **kw)
    msg = str(ei.value)
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"
    return ei.value


# --- round trips --------------------------------------------------------------------------------

def test_frame_raw_raw_bit_exact():
    f = make_frame()
    m = decode(encode_frame(f, "cam0", color="raw", depth="raw"))
    assert isinstance(m, Decoded) and m.type == "frame" and m.stream == "cam0" and m.seq == 7
    assert m.version == FORMAT_VERSION
    g = m.obj
    assert isinstance(g, RGBDFrame)
    assert g.color.dtype == np.uint8 and np.array_equal(g.color, f.color)
    assert g.depth.dtype == np.float32
    assert np.array_equal(g.depth, dequantize_depth(quantize_depth(f.depth)))
    assert np.abs(g.depth - f.depth).max() <= 0.5e-3 + 1e-6
    assert g.intrinsics == f.intrinsics and g.timestamp_ns == f.timestamp_ns and g.seq == f.seq
    assert np.array_equal(g.pose, f.pose) and g.origin == "synthetic"
    assert (m.color_encoding, m.depth_encoding, m.depth_scale, m.pub_ns) == ("raw", "raw", 1000.0, None)
    g.validate()


def test_frame_jpeg_zstd():
    f = make_frame(64, 48, pose=False)
    m = decode(encode_frame(f, "cam1", quality=95, depth="zstd", depth_scale=5000))
    g = m.obj
    assert g.pose is None and g.color.shape == f.color.shape
    assert np.abs(g.color.astype(int) - f.color).mean() < 3.0
    assert np.array_equal(g.depth, dequantize_depth(quantize_depth(f.depth, 5000), 5000))
    assert m.depth_encoding == "zstd" and m.depth_scale == 5000.0


def test_depth_quantisation_invalid_values():
    d = np.array([[0.0, -1.0, np.nan, np.inf, 70.0, 1.2345]], np.float32)
    q = quantize_depth(d)
    assert q.dtype == np.uint16 and q[0, :5].tolist() == [0, 0, 0, 0, 0] and q[0, 5] in (1234, 1235)
    assert dequantize_depth(q, 1000)[0, 5] == np.float32(q[0, 5]) / np.float32(1000)
    # the boundaries, rounding half to even in float64 as np.rint does: -0.0004 m and 65.5355 m are
    # -0.4 and 65535.5 units (invalid: 0 and 65536 -> 0), 65.535 m the largest unit
    d = np.array([[-0.0004, -0.0006, 0.0005, 0.0015, 65.535, 65.5355, -np.inf, 1e30]], np.float32)
    ref = np.rint(d.astype(np.float64) * 1000)
    assert quantize_depth(d).tolist() == [[int(v) if 0 <= v <= 65535 else 0 for v in ref[0]]]


def test_flow_round_trip():
    fl = make_flow()
    m = decode(encode_flow(fl, "cam0"))
    g = m.obj
    assert m.type == "flow" and g.seq == 3 and g.seq_next == 4
    for name in ("points", "displacements", "weights", "pixels", "pixels_next"):
        a, b = getattr(g, name), getattr(fl, name)
        assert a.dtype == np.float64 and np.array_equal(a, b.astype(np.float32).astype(np.float64))
    assert g.intrinsics == fl.intrinsics and g.intrinsics_next == fl.intrinsics_next
    assert g.counts == fl.counts and g.problem == ""
    empty = SceneFlowResult(1, 2, *(np.zeros((0, 3)),) * 2, np.zeros(0), *(np.zeros((0, 2)),) * 2, K, K,
                            {}, "too dark")
    assert decode(encode_flow(empty, "cam0")).obj.problem == "too dark"


def test_motion_round_trip():
    mo = make_motion()
    g = decode(encode_motion(mo, "cam0")).obj
    assert isinstance(g, MotionEstimate)
    for name in ("seq", "seq_next", "group", "estimator", "valid", "reason", "n_points", "inlier_ratio", "rms_px"):
        assert getattr(g, name) == getattr(mo, name)
    assert np.array_equal(g.matrix, mo.matrix) and np.array_equal(g.twist, mo.twist)
    assert np.array_equal(g.zeta_bar, mo.zeta_bar)
    inv = invalid_motion(4, 5, "ga3", "induced", "only 3 pairs")
    h = decode(encode_motion(inv, "cam0")).obj
    assert not h.valid and h.reason == "only 3 pairs" and math.isnan(h.rms_px)
    assert np.array_equal(h.matrix, np.eye(4)) and h.twist.shape == (12,)
    inv.zeta_bar = None
    assert decode(encode_motion(inv, "cam0")).obj.zeta_bar is None


def test_motion_kind_and_covariance_round_trip_and_are_optional():
    """docs/method.md 2.4 / (3k): each motion says how it was known and carries its covariance; a motion
    from before (no such fields) decodes as a fit of unknown covariance; a wrong kind or size is refused."""
    mo = make_motion()
    mo.kind, mo.covariance = "rotation", np.diag(np.arange(1.0, 8.0)) * 1e-6
    g = decode(encode_motion(mo, "cam0")).obj
    assert g.kind == "rotation" and np.array_equal(g.covariance, mo.covariance)
    d = raw(encode_motion(mo, "cam0"))
    del d["kind"], d["covariance"]
    old = decode(repack(d)).obj
    assert old.kind == "fit" and old.covariance is None
    d = raw(encode_motion(mo, "cam0"))
    d["kind"] = "guess"
    rejects(repack(d), "kind", "guess")
    d = raw(encode_motion(mo, "cam0"))
    d["covariance"] = [0.0] * 36
    rejects(repack(d), "covariance", "49")
    mo.kind = "hope"
    with pytest.raises(WireError, match="kind"):
        encode_motion(mo, "cam0")


def test_correction_motion_round_trips_and_is_optional():
    c = make_correction()
    c.motion = "bridge"
    assert decode(encode_correction(c, "cam0")).obj.motion == "bridge"
    d = raw(encode_correction(c, "cam0"))
    del d["motion"]
    assert decode(repack(d)).obj.motion == "fit"
    d["motion"] = "maybe"
    rejects(repack(d), "motion", "maybe")


def test_correction_round_trip():
    c = make_correction()
    m = decode(encode_correction(replace(c, zoom=1.25), "cam0"))
    g = m.obj
    assert isinstance(g, Correction) and np.array_equal(g.matrix, c.matrix)
    assert (g.seq, g.segment, g.keyframe, g.valid, g.reason) == (11, 2, True, True, "")
    assert m.obj.zoom == 1.25
    assert decode(encode_correction(c, "cam0")).obj.zoom is None
    assert decode(encode_correction(c, "cam0")).tag is None
    tagged = decode(encode_correction(c, "cam0", tag=Tag(3, 1, 5, 40))).tag
    assert tagged == (3, 1, 5, 40) and tagged.closed_by == 40
    assert decode(encode_correction(c, "cam0", tag=(3, 1, 5))).tag == Tag(3, 1, 5, None)


def test_the_frames_a_flow_stage_shed_travel_on_the_flow_the_correction_and_the_end():
    """docs/wire-format.md: the optional ``shed`` of a flow (frames shed since the previous flow), a
    correction (frames shed before its frame) and an ``end`` (after the last flow); left out when
    there are none, and a message without it decodes as none shed."""
    fl = make_flow()  # 3 -> 4 ... the seqs shed lie before seq_next
    fl.seq, fl.seq_next = 3, 9
    assert decode(encode_flow(fl, "cam0", shed=[4, 6, 7])).shed == (4, 6, 7)
    assert "shed" not in raw(encode_flow(fl, "cam0")) and decode(encode_flow(fl, "cam0")).shed == ()
    c = make_correction()
    c.shed = (8, 9, 10)
    assert decode(encode_correction(c, "cam0")).obj.shed == (8, 9, 10)
    c.shed = ()
    assert "shed" not in raw(encode_correction(c, "cam0")) and decode(encode_correction(c, "cam0")).obj.shed == ()
    e = decode(encode_end(EndOfStream(20, "done", (18, 20)), "cam0")).obj
    assert (e.seq, e.shed) == (20, (18, 20)) and decode(encode_end(EndOfStream(20), "cam0")).obj.shed == ()


@pytest.mark.parametrize("bad", [[-1], [11], [3.0], ["4"], [True], "4", list(range(10_001))])
def test_a_shed_list_out_of_range_or_not_of_ints_is_refused_naming_it(bad):
    """A correction of frame 11 names frames before it; anything else (a later or negative seq, not an
    int, too many) is refused, naming the field, and never encoded."""
    d = raw(encode_correction(make_correction(), "cam0"))
    d["shed"] = bad
    rejects(repack(d), "shed")
    c = make_correction()
    if isinstance(bad, list) and all(type(x) is int for x in bad):
        c.shed = tuple(bad)
        with pytest.raises(WireError, match="shed"):
            encode_correction(c, "cam0")


def test_stabilized_and_stats_round_trip():
    img = make_frame(40, 30).color
    s = StabilizedImage(12, 400, img, 1.07, ["invalid-motion", "late"])
    g = decode(encode_stabilized(s, "cam0", color="raw")).obj
    assert np.array_equal(g.image, img) and g.zoom == 1.07 and g.flags == s.flags and g.timestamp_ns == 400
    m = decode(encode_stabilized(s, "cam0"))
    assert m.encoding == "jpeg" and np.abs(m.obj.image.astype(int) - img).mean() < 4.0
    st_ = Stats("motion", {"fps": 30.1, "frames": 1200, "state": "ok", "degraded": False, "last_err": None})
    m = decode(encode_stats(st_, "cam0", 5))
    assert m.type == "stats" and m.seq == 5 and m.obj == st_


def test_encode_dispatch():
    assert decode(encode(make_motion(), "a")).type == "motion"
    assert decode(encode(replace(make_correction(), zoom=1.5), stream="b")).obj.zoom == 1.5
    assert decode(encode(make_frame(), "c", color="raw")).type == "frame"
    with pytest.raises(WireError):
        encode(object(), "x")


# --- rejections ---------------------------------------------------------------------------------

def test_reject_not_msgpack_and_truncated():
    rejects(b"", "empty")
    rejects(b"\xc1", "not valid msgpack")
    data = encode_motion(make_motion(), "cam0")
    rejects(data[:-3], "truncated")
    rejects(data + b"\x00", "trailing")
    rejects(bytearray(b"\x91\x01"), "not a msgpack map")
    rejects("text", "expected bytes")


def test_reject_version():
    d = raw(encode_motion(make_motion(), "cam0"))
    d["v"] = 2
    e = rejects(repack(d), "expected 1", "found 2", "'v'", "stream 'cam0'", "seq 9")
    assert e.field == "v" and e.stream == "cam0" and e.seq == 9
    del d["v"]
    rejects(repack(d), "missing format version", "'v'")
    d["v"] = "1"
    rejects(repack(d), "found '1'")


def test_reject_unknown_type_and_envelope():
    d = raw(encode_correction(make_correction(), "cam0"))
    rejects(repack({**d, "type": "video"}), "unknown message type 'video'", "'type'")
    rejects(repack({**d, "seq": -1}), "'seq'")
    rejects(repack({**d, "stream": 5}), "'stream'", "expected str")


def test_reject_missing_and_wrong_type_fields():
    d = raw(encode_motion(make_motion(), "cam0"))
    del d["seq_next"]
    e = rejects(repack(d), "missing field", "'seq_next'", "stream 'cam0'", "seq 9", "type 'motion'")
    assert e.field == "seq_next"
    d = raw(encode_motion(make_motion(), "cam0"))
    rejects(repack({**d, "matrix": "eye"}), "'matrix'", "expected array")
    rejects(repack({**d, "matrix": [1.0] * 15}), "'matrix'", "expected 16")
    rejects(repack({**d, "valid": 1}), "'valid'", "expected bool")
    rejects(repack({**d, "n_points": True}), "'n_points'", "expected int")
    rejects(repack({**d, "group": "so3"}), "'group'", "unknown group")
    rejects(repack({**d, "twist": [0.0] * 6}), "'twist'", "expected 7")
    f = raw(encode_frame(make_frame(), "cam0", color="raw"))
    del f["intrinsics"]["fx"]
    rejects(repack(f), "'intrinsics.fx'", "missing")
    s = raw(encode_stats(Stats("x", {"a": 1}), "cam0", 0))
    s["values"]["a"] = [1, 2]
    rejects(repack(s), "'values.a'")


def test_reject_array_length_and_shape():
    d = raw(encode_flow(make_flow(), "cam0"))
    d["points"]["data"] = d["points"]["data"][:-4]
    rejects(repack(d), "'points.data'", "do not match", "seq 3")
    d = raw(encode_flow(make_flow(), "cam0"))
    d["points"]["dtype"] = "<f8"
    rejects(repack(d), "'points.dtype'")
    d = raw(encode_flow(make_flow(), "cam0"))
    d["weights"] = raw(encode_flow(make_flow(10), "cam0"))["weights"]
    rejects(repack(d), "'weights'", "rows")
    f = raw(encode_frame(make_frame(), "cam0", color="raw", depth="raw"))
    f["depth"]["data"] += b"\x00\x00"
    rejects(repack(f), "'depth.data'")
    f = raw(encode_frame(make_frame(), "cam0", depth="zstd"))
    f["depth"]["shape"] = [24, 31]
    rejects(repack(f), "'depth.data'", "content size")
    f["depth"]["data"] = b"\x28\xb5\x2f\xfd garbage"
    rejects(repack(f), "'depth.data'")
    f = raw(encode_frame(make_frame(), "cam0", color="raw"))
    f["intrinsics"]["width"] = 33
    rejects(repack(f), "'color'", "intrinsics")


def test_reject_non_finite():
    d = raw(encode_motion(make_motion(), "cam0"))
    rejects(repack({**d, "matrix": [float("nan")] + [0.0] * 15}), "'matrix'", "non-finite")
    rejects(repack({**d, "inlier_ratio": float("inf")}), "'inlier_ratio'", "non-finite")
    assert math.isnan(decode(repack({**d, "rms_px": float("nan")})).obj.rms_px)  # allowed
    fl = make_flow()
    fl.points[0, 0] = np.nan
    rejects(encode_flow(fl, "cam0"), "'points.data'", "non-finite")
    c = raw(encode_correction(make_correction(), "cam0"))
    rejects(repack({**c, "zoom": float("nan")}), "'zoom'")
    rejects(repack({**c, "zoom": -1.0}), "'zoom'")
    rejects(repack({**c, "closed_by": "frame 40"}), "'closed_by'")
    with pytest.raises(WireError, match="matrix"):
        encode_correction(Correction(0, np.full((4, 4), np.nan), 0, False), "cam0")


def test_a_jpeg_colour_decodes_to_its_own_grey_for_the_flow():
    """``color="luma"`` (the flow service) decodes a JPEG's Y channel only, ``"bgr+luma"`` (the recording's
    frames offline) the colour and that same grey: the flow reads the same grey in both; raw colour has none."""
    import cv2

    f = make_frame(64, 48, seed=3)
    data = encode_frame(f, "cam0", quality=80)
    jpeg = np.frombuffer(raw(data)["color"]["data"], np.uint8)
    own = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE)
    bgr, both, luma = (decode(data, color=c).obj for c in ("bgr", "bgr+luma", "luma"))
    assert bgr.luma is None and np.array_equal(bgr.grey(), cv2.cvtColor(bgr.color, cv2.COLOR_BGR2GRAY))
    assert np.array_equal(both.color, bgr.color) and np.array_equal(both.luma, own) and np.array_equal(luma.luma, own)
    assert np.array_equal(luma.grey(), both.grey())
    assert not np.array_equal(own, bgr.grey())  # the JPEG's grey is not the decoded colour's (chroma, rounding)
    assert luma.color.shape == f.color.shape and not luma.color.flags.writeable and not luma.color.any()
    luma.validate()
    assert np.array_equal(luma.depth, bgr.depth)
    for c in ("bgr", "bgr+luma", "luma"):
        g = decode(encode_frame(f, "cam0", color="raw"), color=c).obj
        assert g.luma is None and np.array_equal(g.color, f.color)
    with pytest.raises(ValueError, match="color must be one of"):
        decode(data, color="grey")



def test_a_jpeg_whose_grey_fails_to_decode_is_refused(monkeypatch):
    import cv2

    data = encode_frame(make_frame(64, 48), "cam0")
    real = cv2.imdecode
    for result in (lambda buf: None, lambda buf: np.zeros((4, 4), np.uint8)):  # libjpeg gave up; another size
        monkeypatch.setattr(cv2, "imdecode", lambda buf, flags, r=result: r(buf) if flags == cv2.IMREAD_GRAYSCALE
                            else real(buf, flags))
        assert decode(data).obj.luma is None
        for c in ("luma", "bgr+luma"):
            with pytest.raises(WireError, match="JPEG failed to decode.*'color.data'"):
                decode(data, color=c)


def test_a_luma_must_match_the_colour_and_a_new_colour_drops_it():
    from quick_stream.core.frame import FrameError

    f = make_frame()
    g = f.with_(luma=np.zeros(f.color.shape[:2], np.uint8))
    assert g.validate() is g and g.grey() is g.luma
    assert f.with_(luma=g.luma).with_(color=f.color.copy()).luma is None
    for bad in (np.zeros((5, 5), np.uint8), np.zeros(f.color.shape[:2], np.float32)):
        with pytest.raises(FrameError, match="luma"):
            f.with_(luma=bad).validate()


def test_reject_bad_image():
    f = raw(encode_frame(make_frame(), "cam0"))
    f["color"]["data"] = b"not a jpeg at all"
    rejects(repack(f), "'color.data'", "not a JPEG")
    f = raw(encode_frame(make_frame(), "cam0"))
    f["color"]["shape"] = [48, 64, 3]
    rejects(repack(f), "'color.data'", "32x24")
    f = raw(encode_frame(make_frame(), "cam0"))
    data = f["color"]["data"]
    f["color"]["data"] = data[:200] + b"\xff\xd9"
    try:  # libjpeg may decode a damaged body with warnings: either outcome, never a crash
        decode(repack(f))
    except WireError as e:
        assert "color" in str(e)
    f["color"]["enc"] = "png"
    rejects(repack(f), "'color.enc'", "png")


def test_reject_oversized_and_hostile_headers():
    data = encode_frame(make_frame(), "cam0", color="raw")
    rejects(data, "max_bytes=1000", max_bytes=1000)
    assert decode(data, max_bytes=len(data)).type == "frame"
    for hostile in (b"\xc6\xff\xff\xff\xff", b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff",
                    b"\xdb\xff\xff\xff\xff", b"\x81\xa1v\xc6\x7f\xff\xff\xff" + b"\x00" * 8):
        rejects(hostile)
    d = raw(encode_frame(make_frame(), "cam0", color="raw", depth="raw"))
    d["color"]["shape"] = [2**30, 2**30, 3]
    rejects(repack(d), "'color.shape'")


# --- fuzz ---------------------------------------------------------------------------------------

BASES = small_messages()
VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=8),
    st.binary(max_size=16), st.lists(st.integers(-5, 5), max_size=20),
    st.dictionaries(st.text(max_size=4), st.integers(-2**63, 2**64 - 1), max_size=3),
)


def _check(data: bytes) -> None:
    try:
        m = decode(data)
    except WireError:
        return
    assert isinstance(m, Decoded) and m.type in ("frame", "flow", "motion", "correction", "stabilized", "stats")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(st.binary(max_size=200))
def test_fuzz_random_bytes(data):
    _check(data)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(st.sampled_from(range(len(BASES))), st.data())
def test_fuzz_mutations(i, data):
    msg = BASES[i]
    op = data.draw(st.sampled_from(["truncate", "flip", "delete", "replace"]))
    if op == "truncate":
        _check(msg[: data.draw(st.integers(0, len(msg) - 1))])
    elif op == "flip":
        b = bytearray(msg)
        for _ in range(data.draw(st.integers(1, 4))):
            b[data.draw(st.integers(0, len(b) - 1))] ^= data.draw(st.integers(1, 255))
        _check(bytes(b))
    else:
        d = raw(msg)
        target = d
        key = data.draw(st.sampled_from(sorted(d)))
        if isinstance(d[key], dict) and d[key] and data.draw(st.booleans()):
            target = d[key]
            key = data.draw(st.sampled_from(sorted(target)))
        if op == "delete":
            del target[key]
        else:
            target[key] = data.draw(VALUES)
        _check(repack(d))


def test_a_frame_larger_than_the_maximum_is_refused_from_its_header(monkeypatch):
    """An 8192x8192 JPEG in a small message (it pushed flow and render to ~1.1 GB): refused from the
    declared shape before anything is decoded; the maximum is configurable per process."""
    from quick_stream.stream.wire import pixels

    d = raw(encode_frame(make_frame(), "cam0"))
    d["color"]["shape"] = [8192, 8192, 3]
    d["intrinsics"]["width"] = d["intrinsics"]["height"] = 8192
    rejects(repack(d), "'color.shape'", "8192x8192 outside 1..4096")
    monkeypatch.setattr(pixels, "MAX_IMAGE_SIDE", 4096)  # restored after the test
    monkeypatch.setattr(pixels, "MAX_IMAGE_PIXELS", pixels.MAX_IMAGE_PIXELS)
    pixels.set_max_image_side(16384)
    pixels.set_max_image_pixels(8192 * 8192)
    with pytest.raises(WireError) as e:  # allowed now: the JPEG's own header (32x24) disagrees, still not decoded
        decode(repack(d))
    assert "JPEG is 32x24 but shape says 8192x8192" in str(e.value)
    with pytest.raises(ValueError, match="16..16384"):
        pixels.set_max_image_side(100_000)


def test_a_frame_within_the_side_limit_but_with_too_many_pixels_is_refused_from_its_header(monkeypatch):
    """A 4096x4096 frame is within the side limit, yet one such frame took flow and render ~340 MB each:
    the pixel limit (default 1920x1200, --max-frame-pixels) refuses it from the declared shape, colour
    and depth alike, before decoding; raised, the same message gets as far as its JPEG header."""
    from quick_stream.stream.wire import pixels

    d = raw(encode_frame(make_frame(), "cam0"))
    d["color"]["shape"] = [4096, 4096, 3]
    d["intrinsics"]["width"] = d["intrinsics"]["height"] = 4096
    rejects(repack(d), "'color.shape'", "4096x4096 has 16777216 pixels, above the limit of 2304000")
    d = raw(encode_frame(make_frame(), "cam0"))
    d["depth"]["shape"] = [2000, 2000]
    rejects(repack(d), "'depth.shape'", "4000000 elements exceed the limit 2304000")
    d = raw(encode_frame(make_frame(), "cam0"))
    d["color"]["shape"] = [1200, 1920, 3]  # exactly at the limit: on to the JPEG's own header
    d["intrinsics"]["width"], d["intrinsics"]["height"] = 1920, 1200
    with pytest.raises(WireError) as e:
        decode(repack(d))
    assert "JPEG is 32x24 but shape says 1920x1200" in str(e.value)
    monkeypatch.setattr(pixels, "MAX_IMAGE_PIXELS", pixels.MAX_IMAGE_PIXELS)  # restored after the test
    pixels.set_max_image_pixels(4096 * 4096)
    d = raw(encode_frame(make_frame(), "cam0"))
    d["color"]["shape"] = [4096, 4096, 3]
    d["intrinsics"]["width"] = d["intrinsics"]["height"] = 4096
    with pytest.raises(WireError) as e:
        decode(repack(d))
    assert "JPEG is 32x24 but shape says 4096x4096" in str(e.value)
    with pytest.raises(ValueError, match="256.."):
        pixels.set_max_image_pixels(10)


# --- flow, version 2: the compact layout (wire/flowpack.py) ---------------------------------------

@pytest.fixture(scope="module")
def scene_flows():
    """Flows as the scene flow makes them (synthetic 160x120): what the flow service publishes."""
    from quick_stream.core.sceneflow import SceneFlow
    from quick_stream.io.sources import open_source

    fr = list(open_source("synthetic:frames=6,width=160,height=120"))
    sf = SceneFlow()
    return [sf.compute(a, b) for a, b in zip(fr, fr[1:])]


def _bits_equal(a, b) -> bool:
    a, b = np.ascontiguousarray(a, np.float64), np.ascontiguousarray(b, np.float64)
    return a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


FLOW_ARRAYS = ("points", "displacements", "weights", "pixels", "pixels_next")


def test_compact_flow_round_trip_is_bit_exact_and_small(scene_flows):
    from quick_stream.stream.wire.codec import encode_array, pack

    for fl in scene_flows:
        data = encode_flow(fl, "cam0")
        m = decode(data)
        assert m.version == 2 and raw(data)["v"] == 2 and "grid" in raw(data) and "points" not in raw(data)
        for name in FLOW_ARRAYS:  # what motion gets from the wire is what it gets in-process
            assert _bits_equal(getattr(m.obj, name), getattr(fl, name)), name
        assert encode_flow(m.obj, "cam0") == data  # re-encoding is stable (rerun compares bytes)
        # version 1 (five float32 arrays, old recordings) still decodes, to the same numbers
        v1 = {"seq_next": fl.seq_next, **{n: encode_array(getattr(fl, n), "<f4") for n in FLOW_ARRAYS},
              "intrinsics": raw(data)["intrinsics"], "intrinsics_next": raw(data)["intrinsics_next"],
              "counts": fl.counts, "problem": ""}
        old = pack(v1, "flow", "cam0", fl.seq, version=1)
        assert len(data) < len(old) / 4
        g = decode(old)
        assert g.version == 1 and all(_bits_equal(getattr(g.obj, n), getattr(fl, n)) for n in FLOW_ARRAYS)


def test_flows_the_compact_layout_cannot_hold_go_as_version_1(scene_flows):
    fl = make_flow()  # random pixels: not on a grid
    assert raw(encode_flow(fl, "cam0"))["v"] == 1
    g = scene_flows[0]
    for change in ("pixels", "pixels_next", "weights", "points"):
        h = SceneFlowResult(g.seq, g.seq_next, g.points.copy(), g.displacements.copy(), g.weights.copy(),
                            g.pixels.copy(), g.pixels_next.copy(), g.intrinsics, g.intrinsics_next, g.counts)
        arr = getattr(h, change)
        arr[0] = arr[0] + (0.25 if change != "pixels" else 1.0)  # off the grid order / the lift (float32-exact)
        d = raw(encode_flow(h, "cam0"))
        assert d["v"] == (2 if change == "weights" else 1), change  # weights other than 1 are carried
        got = decode(encode_flow(h, "cam0")).obj
        assert _bits_equal(getattr(got, change), getattr(h, change)), change
    empty = SceneFlowResult.empty(*[make_frame()] * 2, "too dark")
    m = decode(encode_flow(empty, "cam0"))
    assert m.version == 2 and len(m.obj) == 0 and m.obj.problem == "too dark"


def test_compact_flow_rejections(scene_flows):
    from quick_stream.stream.wire import flowpack

    good = raw(encode_flow(scene_flows[0], "cam0"))
    n = good["n"]

    def edit(fn):
        d = msgpack.unpackb(msgpack.packb(good, use_bin_type=True), raw=False)
        fn(d)
        return repack(d)

    rejects(edit(lambda d: d.update(n=n + 1)), "'grid.mask'", "samples")
    rejects(edit(lambda d: d["grid"].update(mask=d["grid"]["mask"][:-1])), "'grid.mask'", "bytes")
    rejects(edit(lambda d: d["grid"].update(cols=1 << 13, rows=1 << 12)), "'grid.cols'", "exceed")
    rejects(edit(lambda d: d.update(offset_exp=65)), "'offset_exp'")
    rejects(edit(lambda d: d["depth"].update(shape=[n + 1])), "'depth.shape'")
    rejects(edit(lambda d: d["offset"].update(dtype="<f4")), "'offset.dtype'")
    rejects(edit(lambda d: d["depth_change"].update(enc="raw")), "'depth_change.enc'")
    rejects(edit(lambda d: d["depth"].update(data=b"\x28\xb5\x2f\xfd junk")), "'depth.data'")
    rejects(edit(lambda d: d.update(depth=flowpack.pack_array(np.full(n, np.inf), "<f4"))), "'depth'", "non-finite")
    rejects(edit(lambda d: d.update(depth=flowpack.pack_array(np.full(n, 3e38), "<f4"),
                                    offset_exp=-64)), "non-finite")
    rejects(edit(lambda d: d.pop("grid")), "'grid'", "missing")
    cells = good["grid"]["cols"] * good["grid"]["rows"]
    if cells % 8:  # a bit set past the last cell
        rejects(edit(lambda d: d["grid"].update(mask=d["grid"]["mask"][:-1] + bytes([d["grid"]["mask"][-1] | 0x80]))),
                "'grid.mask'", "past the last cell")
    rejects(edit(lambda d: d.update(v=3)), "'v'", "expected 1 to 2", "found 3", "'flow'")
    rejects(edit(lambda d: d.update(v=1)), "'points'", "missing")  # a version-1 decoder's view of it
