"""The flow service's frame gate: :class:`~quick_stream.core.admission.FlowAdmission` fed from the wire.

A frame is offered to the admission policy as it arrives, before it takes a place in flow's queue
(:attr:`~quick_stream.stream.inbox.Inbox.admit`, with the envelope its check read), and again when
flow takes it from the queue, before decoding it (:meth:`FrameGate.admit`, the service loop's
``admit``: its seq read from the envelope, :func:`~quick_stream.stream.wire.codec.peek`); a frame
the queue drops for room is named too (:attr:`~quick_stream.stream.inbox.Inbox.on_drop`). A shed
frame is never decoded. The policy learns how far the stages after flow have got from their own
messages (the motion stage's ``motion``, the newest frame it reached; the ``stabilized`` output) and
which of the services are up from the liveliness tokens, as a live capture's shedding does
(:class:`~quick_stream.stream.capture.OutputCredit`). While a restarted flow works through the
frames' history (the inbox's catch-up bound) nothing is shed: those frames are owed. Callbacks
arrive on zenoh's threads, the loop's calls on its own: one lock.
"""
from __future__ import annotations

import threading
import time

import zenoh

from ..core.admission import FlowAdmission
from ..core.pacing import CREDIT_STAGES
from . import keys
from .inbox import Inbox
from .runtime import ServiceRuntime
from .wire import WireError
from .wire.codec import peek, unpack


class FrameGate:
    """Which frames the flow service queues, decodes and takes (module docstring)."""

    def __init__(self, rt: ServiceRuntime, stream: str, inbox: Inbox, admission: FlowAdmission) -> None:
        self.inbox, self.admission = inbox, admission
        self._lock = threading.Lock()
        inbox.admit, inbox.on_drop = self._arrived, self._dropped
        for stage in CREDIT_STAGES:
            rt.subscribe(keys.key(stream, stage), self._on_output)
        rt.watch_health(self._on_health)

    @property
    def catching_up(self) -> bool:
        return self.inbox.capacity > self.inbox.base_capacity

    def _on_health(self, service: str, up: bool) -> None:
        with self._lock:
            self.admission.set_up(service, up, time.monotonic())

    def _on_output(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        if str(sample.key_expr).endswith("/stabilized"):  # its envelope says it (the image is not read)
            env = peek(data)
        else:  # a motion reached the frame its pair ends at
            try:
                r = unpack(data)
            except WireError:
                return
            env = (r.type, r.d.get("seq_next"))
        if env is None or env[0] not in CREDIT_STAGES or not isinstance(env[1], int) or isinstance(env[1], bool):
            return
        with self._lock:
            self.admission.progressed(env[0], env[1], time.monotonic())

    def _arrived(self, key_expr: str, payload: bytes, env: tuple[str, int, int | None] | None) -> bool:
        if env is None or env[0] != "frame" or self.catching_up:
            return True  # an end marker, a message its consumer refuses and reports, the history owed
        with self._lock:
            return self.admission.offer(env[1], time.monotonic())

    def _dropped(self, key_expr: str, payload: bytes) -> None:
        env = peek(payload)
        if env is not None and env[0] == "frame":
            with self._lock:
                self.admission.dropped(env[1])

    def admit(self, key_expr: str, payload: bytes) -> bool:
        """Whether to decode and take this message: anything but a frame, and a frame taken from the
        queue with at most the backlog behind it (or while catching up)."""
        env = peek(payload)
        if env is None or env[0] != "frame" or self.catching_up:
            return True
        with self._lock:
            return self.admission.take(env[1], len(self.inbox))

    def taken(self, seq: int) -> None:
        with self._lock:
            self.admission.taken(seq)

    def take_shed(self) -> list[int]:
        with self._lock:
            return self.admission.take_shed()

    def restart(self) -> None:
        with self._lock:
            self.admission.restart()

    def stats(self) -> dict[str, int]:
        with self._lock:
            return self.admission.stats()
