"""A recording's images stored once: in the Foxglove image record, referenced by the wire record.

A ``frame`` message's colour JPEG and a ``stabilized`` message's JPEG are what a recording
is mostly made of, and both the exact-replay msgpack channel and the Foxglove
``CompressedImage`` channel need them. The recorder writes each JPEG once, in the
``foxglove.CompressedImage`` record on ``/<stream>/color`` (resp. ``/<stream>/stabilized``),
and on the msgpack channel the wire message with that image map's ``data`` replaced by
``ref``: the MCAP sequence number of the image record, written just before it in the same
file, with the same log time (docs/recording.md, "Images stored once").

Readers put the JPEG back: :class:`Rejoiner` turns a stored message into the exact bytes
the recorder received (checked when storing: only a message that re-packs to itself byte
for byte is stored apart, anything else is stored whole). A stored message whose image
record is missing (a damaged file) is passed on as stored; decoding it then fails naming
the missing image (:func:`quick_stream.stream.wire.pixels.decode_image`).
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable, NamedTuple

import msgpack

from ..stream import keys
from ..stream.wire import WireError
from ..stream.wire.codec import unpack
from . import foxglove

REF = "ref"  # the key that replaces an image map's "data" in a stored message
CHANNEL_OF_STAGE = {"frame": "color", "stabilized": "stabilized"}  # stage -> its Foxglove image channel
_KEEP = 64  # image records held for their wire record (it comes right after its image)


class ApartImage(NamedTuple):
    """A wire message with a JPEG image: the unpacked map, the JPEG and its stamp."""

    fields: dict[str, Any]
    image_field: str  # "color" (frame) or "image" (stabilized)
    jpeg: bytes
    stream: str
    stage: str
    timestamp_ns: int  # wall clock: the frame's pub_ns (stabilized: src_pub_ns), else the log time
    exact: bool  # the map re-packs to the message byte for byte: it can be stored apart


def image_topic(stream: str, stage: str) -> str | None:
    """The Foxglove image topic a stage's images are stored on (None for stages without images)."""
    channel = CHANNEL_OF_STAGE.get(stage)
    return None if channel is None else foxglove.topic(stream, channel)


def _pack(fields: dict[str, Any]) -> bytes:
    return msgpack.packb(fields, use_bin_type=True)


def _image_field(data: bytes) -> tuple[Any, str, Any] | None:
    """(the unpacked message, the name of its image field, that field's value) of a ``frame`` or
    ``stabilized`` message; None for other types and for bytes that do not unpack."""
    try:
        r = unpack(data)
    except WireError:
        return None
    name = foxglove.IMAGE_FIELD.get(r.type)
    return (r, name, r.d.get(name)) if name else None


def split(payload: bytes, log_time_ns: int) -> ApartImage | None:
    """The parts of a ``frame``/``stabilized`` message with a JPEG image; None for raw images,
    other types and messages that do not unpack."""
    r, name, img = _image_field(payload) or (None, "", None)
    if not isinstance(img, dict) or img.get("enc") != "jpeg" or not isinstance(img.get("data"), bytes):
        return None
    stamp = r.d.get("pub_ns" if r.type == "frame" else "src_pub_ns")
    if not isinstance(stamp, int) or isinstance(stamp, bool) or stamp < 0:
        stamp = log_time_ns
    exact = REF not in img and _pack(r.d) == bytes(payload)
    return ApartImage(r.d, name, img["data"], r.stream, r.type, int(stamp), exact)


def stored_message(parts: ApartImage, ref: int) -> bytes:
    """The message as stored on the msgpack channel: the image's ``data`` replaced by ``ref``, in place."""
    img = parts.fields[parts.image_field]
    stored = {(REF if k == "data" else k): (int(ref) if k == "data" else v) for k, v in img.items()}
    return _pack({k: (stored if k == parts.image_field else v) for k, v in parts.fields.items()})


def image_message(parts: ApartImage) -> bytes:
    """The ``foxglove.CompressedImage`` record holding the JPEG."""
    stabilized = parts.stage == "stabilized"
    return foxglove.compressed_image(parts.timestamp_ns, parts.jpeg, "jpeg",
                                     foxglove.camera_frame(parts.stream, stabilized))


def write_message(write: Callable[[str, bytes], int], key_expr: str, payload: bytes, log_time_ns: int,
                  images: bool = True) -> int:
    """Log one wire message through ``write(topic, data) -> sequence``; returns the bytes written.

    ``images``: a ``frame``/``stabilized`` message with a JPEG also gets its Foxglove image record
    (written first), and the message is stored referencing it when that gives it back byte for byte
    (else it is stored whole: its JPEG is then in both records)."""
    parts = None
    if images:
        stream, stage = keys.parse(key_expr)
        topic = image_topic(stream, stage)
        parts = split(payload, log_time_ns) if topic is not None else None
    if parts is None:
        write(key_expr, payload)
        return len(payload)
    image = image_message(parts)
    ref = write(topic, image)
    apart = parts.exact and (parts.stream, parts.stage) == (stream, stage)
    stored = stored_message(parts, ref) if apart else bytes(payload)
    write(key_expr, stored)
    return len(image) + len(stored)


def _rejoin(data: bytes, jpeg_of: Callable[[str, str, int], bytes | None]) -> bytes:
    """``data`` with its stored-apart image put back (unchanged when it has none or it is missing)."""
    r, name, img = _image_field(data) or (None, "", None)
    if not isinstance(img, dict) or "data" in img or type(img.get(REF)) is not int:
        return data
    jpeg = jpeg_of(r.stream, r.type, img[REF])
    if jpeg is None:
        return data
    whole = {("data" if k == REF else k): (jpeg if k == REF else v) for k, v in img.items()}
    return _pack({k: (whole if k == name else v) for k, v in r.d.items()})


class Rejoiner:
    """Puts stored-apart images back into wire messages as a recording is read in order.

    ``topics``: what the caller asked for (None: everything). :attr:`read_topics` adds the image
    topics the wanted ``frame``/``stabilized`` channels may refer to; :meth:`take` returns each
    record's bytes to hand out (wire messages rejoined), or None for an image record read only to
    be rejoined."""

    def __init__(self, topics: list[str] | None = None) -> None:
        self.wanted = None if topics is None else set(topics)
        self.read_topics: list[str] | None = None
        self._image_topics: set[str] = set()
        if topics is not None:
            extra = []
            for t in topics:
                try:
                    it = image_topic(*keys.parse(t))
                except ValueError:
                    continue
                if it is not None:
                    self._image_topics.add(it)
                    extra.append(it)
            self.read_topics = list(dict.fromkeys([*topics, *extra]))
        self._images: OrderedDict[tuple[str, int], bytes] = OrderedDict()
        self.missing = 0  # stored messages whose image record was not found

    def _is_image_topic(self, topic: str) -> bool:
        if self.wanted is not None:
            return topic in self._image_topics
        parts = topic.split("/")
        return len(parts) == 3 and parts[0] == "" and parts[2] in CHANNEL_OF_STAGE.values()

    def _jpeg(self, stream: str, stage: str, ref: int) -> bytes | None:
        topic = image_topic(stream, stage)
        data = self._images.pop((topic, ref), None)
        if data is None:
            self.missing += 1
            return None
        try:
            return foxglove.parse("foxglove.CompressedImage", data).data
        except ValueError:
            self.missing += 1
            return None

    def take(self, topic: str, sequence: int, data: bytes) -> bytes | None:
        """The bytes to hand out for one record read (None: an image read only to rejoin)."""
        if self._is_image_topic(topic):
            self._images[(topic, sequence)] = bytes(data)
            while len(self._images) > _KEEP:
                self._images.popitem(last=False)
            return bytes(data) if self.wanted is None or topic in self.wanted else None
        if topic.startswith(keys.PREFIX + "/") and topic.rpartition("/")[2] in CHANNEL_OF_STAGE:
            return _rejoin(bytes(data), self._jpeg)
        return data


__all__ = ["ApartImage", "REF", "Rejoiner", "image_message", "image_topic", "split", "stored_message",
           "write_message"]
