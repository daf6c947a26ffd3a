"""The one service loop: receive, decode and check, dispatch, contain, stats, stop.

Every receiving service (flow, motion, render, recorder) hands the runtime its inboxes, one
:class:`Input` each with a handler per message type, and calls :meth:`Loop.serve`; the loop is
the runtime's (docs/architecture.md, "The service loop"):

* each pass publishes the stats when due, then takes from every input in order what its
  ``take`` allows (one message, the ones pending when its turn came, or all until ``paused``),
  then calls the service's ``tick`` (work that is due whether or not a message came: a render
  release waiting for its frames, the end of a stream);
* a message is decoded and checked (:meth:`ServiceRuntime.decode`: one that does not decode, is of
  another stream or of a type the input has no handler for is logged and counted in
  ``decode_errors``) and handed to its type's handler under :meth:`ServiceRuntime.contained` (an
  unexpected exception is logged with its traceback and counted in ``internal_errors``; the
  service goes on);
* after an ``end`` the inbox stops skipping what a predecessor handled (``skip_through``): a new
  stream follows, none of which was handled before;
* with nothing to do it sleeps until a message arrives (``idle_s`` at most); on SIGTERM/SIGINT it
  ends, runs ``on_stop`` and publishes the last stats with ``state`` ``stopped`` (or ``final_state``).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Callable

from .inbox import Inbox
from .wire import COLOR_MODES, Decoded

Handler = Callable[[Decoded], Any]
TAKES = ("one", "pending", "all")


@dataclass
class Input:
    """One inbox of a service and what the service does with its messages.

    ``on``: a handler per message type the inbox carries (``end`` included; None: accepted and
    ignored); every other type is refused (``decode_errors``). ``raw``: instead of decoding, each
    item as it arrived, ``raw(key, payload, arrival_ns)`` (the recorder). ``take``: per pass,
    ``one`` message, the ``pending`` ones (those queued when this input's turn came, so messages
    arriving faster than they are handled never starve the other inputs) or ``all`` of them.
    ``paused()``: True while the input is not to be read (render: the corrections of the next
    stream wait while the last one ends). ``label(msg)`` (``raw``: ``label(key)``) names the
    data message in a contained error (default, and for ``end``: its type and seq). ``color``:
    what a frame's JPEG colour decodes to (:func:`~quick_stream.stream.wire.decode`; the flow
    service needs only its grey). ``admit(key, payload)``: asked before a message is decoded;
    False: it is let go undecoded (the flow service's shedding, counted by its policy). ``lazy``:
    every field is checked but images and depth maps are left undecoded (``pixels=False``; the depth's
    compressed stream, checked by the inbox on arrival, is not decompressed again), the handler
    finding the message's bytes in ``payload`` to decode when it needs the pixels (the render
    service: when the frame's correction arrives)."""

    inbox: Inbox
    on: dict[str, Handler | None] = field(default_factory=dict)
    raw: Callable[[str, bytes, int], Any] | None = None
    take: str = "one"
    paused: Callable[[], bool] | None = None
    label: Callable[[Any], str] | None = None
    color: str = "bgr"
    admit: Callable[[str, bytes], bool] | None = None
    lazy: bool = False

    def __post_init__(self) -> None:
        if self.take not in TAKES:
            raise ValueError(f"take must be one of {', '.join(TAKES)}, got {self.take!r}")
        if self.color not in COLOR_MODES:
            raise ValueError(f"color must be one of {', '.join(COLOR_MODES)}, got {self.color!r}")
        if (self.raw is None) == (not self.on):
            raise ValueError("an input has either handlers per message type or a raw handler")

    def is_paused(self) -> bool:
        return self.paused is not None and self.paused()


class Loop:
    """The service loop of :class:`~quick_stream.stream.runtime.ServiceRuntime` (a mixin: the
    runtime provides the stop event, the decoder, containment, stats and the wait)."""

    stop: threading.Event
    errors: dict[str, int]

    def serve(self, inputs: list[Input], stats: Callable[[], dict[str, Any]], *,
              tick: Callable[[], Any] | None = None, idle_s: float | Callable[[], float] = 0.2,
              on_stop: Callable[[], Any] | None = None, final_state: Callable[[], str] | None = None) -> None:
        """Run the service until it is stopped (module docstring). ``stats()``: the service's own
        values (the runtime adds its counters, the inboxes' and the publishers'); ``tick()``: after
        every pass; ``idle_s``: the longest sleep when a pass found nothing; ``on_stop()``: once
        stopped, before the last stats; ``final_state()``: their ``state`` (default ``stopped``)."""
        self.stats_source = stats
        self.errors.setdefault("internal_errors", 0)
        if any(i.raw is None for i in inputs):
            self.errors.setdefault("decode_errors", 0)
        while not self.stop.is_set():
            self.maybe_stats()
            got = False
            for inp in inputs:
                got = self._take(inp) or got
            if tick is not None:
                tick()
            if not got:
                self.wait(idle_s() if callable(idle_s) else idle_s, [i.inbox for i in inputs if not i.is_paused()])
        if on_stop is not None:
            on_stop()
        self.publish_stats({**stats(), "state": final_state() if final_state is not None else "stopped"})

    def _take(self, inp: Input) -> bool:
        """Handle what ``inp.take`` allows of ``inp``'s queue now; whether there was anything."""
        left = 1 if inp.take == "one" else len(inp.inbox) if inp.take == "pending" else -1
        got = False
        while left != 0 and not inp.is_paused():
            item = inp.inbox.pop()
            if item is None:
                break
            got, left = True, left - 1
            self.handle(inp, *item)
        return got

    def handle(self, inp: Input, key_expr: str, payload: bytes, arrival_ns: int) -> None:
        """One message of ``inp``: decoded, checked and dispatched to its handler, contained."""
        if inp.raw is not None:
            with self.contained((lambda: inp.label(key_expr)) if inp.label else f"message on {key_expr}"):
                inp.raw(key_expr, payload, arrival_ns)
            return
        arrivals = getattr(inp.inbox, "arrivals", None)
        depth = arrivals.depth_of(payload) if arrivals is not None else None  # the check's, kept (flow)
        if inp.admit is not None and not inp.admit(key_expr, payload):
            return
        last = getattr(arrivals, "last", None)  # the check's decode, when whole
        # (a lazy input's depth stream is not decompressed again: the inbox checked it on arrival)
        msg = self.decode(key_expr, payload, tuple(inp.on), inp.color,
                          checked=last[1] if last is not None and last[0] is payload else None,
                          pixels=not inp.lazy, depth_raw=depth, streams=False)
        if msg is None:
            return
        if inp.lazy:
            msg.payload = payload
        handler = inp.on[msg.type]
        if handler is not None:
            data = inp.label is not None and msg.type != "end"  # an end marker is named by its type and seq
            with self.contained((lambda: inp.label(msg)) if data else f"{msg.type} {msg.seq}"):
                handler(msg)
        if msg.type == "end":
            inp.inbox.skip_through = None  # a new stream may follow: none of it was handled by a predecessor

    # provided by the runtime
    def maybe_stats(self, values: Callable[[], dict[str, Any]] | None = None) -> None:
        raise NotImplementedError

    def publish_stats(self, values: dict[str, Any] | None = None) -> None:
        raise NotImplementedError

    def wait(self, timeout_s: float, inboxes: list[Inbox] | None = None) -> None:
        raise NotImplementedError

    def decode(self, key_expr: str, data: bytes, expect: tuple[str, ...], color: str = "bgr",
               checked: Decoded | None = None, pixels: bool = True, depth_raw: bytes | None = None,
               streams: bool = True) -> Decoded | None:
        raise NotImplementedError

    def contained(self, what: str | Callable[[], str]) -> Any:
        raise NotImplementedError
