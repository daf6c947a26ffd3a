"""The command lines of one stream's processes, from the pipeline's table (:mod:`.topology`).

``quick-stream up``, ``quick-stream bench pipeline`` and the test harness start the same services;
each says only what differs (zenoh flags per service, each service's own arguments, another module
for a stage, which services run), and the order, the modules and the capture's ``--wait-for`` come
from here.
"""
from __future__ import annotations

from typing import Callable, Mapping, Sequence

from . import topology
from .launcher import ServiceSpec


def module_of(service: str) -> str:
    """The service's module (``python -m``)."""
    return f"quick_stream.services.{service}"


def stream_specs(zflags: Callable[[str], Sequence[str]], own: Mapping[str, Sequence[str]] | None = None, *,
                 run: Sequence[str] = topology.SERVICES, modules: Mapping[str, str] | None = None,
                 name: Callable[[str], str] = str) -> list[ServiceSpec]:
    """One stream's services of ``run`` in start order (recorder, flow, motion, render, capture:
    :data:`~.topology.START_ORDER`), each ``python -m <module> <zflags(service)> <own[service]>``. The
    capture starts sending once every other service started here is up (``--wait-for``, by their
    liveliness tokens: service names, not ``name``'s) and may finish (its source ends). ``modules``:
    another module for a service (a test tool such as a slowed render); ``name``: each process's name
    in the supervisor (``flow-cam1`` with several streams)."""
    own, modules = own or {}, modules or {}
    unknown = set(run) - set(topology.SERVICES)
    if unknown:
        raise ValueError(f"no such services {sorted(unknown)}; the pipeline's: {list(topology.SERVICES)}")
    order = [s for s in topology.START_ORDER if s in run]
    specs = []
    for s in order:
        argv = ["-m", modules.get(s, module_of(s)), *zflags(s), *own.get(s, ())]
        if s == topology.SOURCE:
            argv += ["--wait-for", ",".join(o for o in order if o != s)]
        specs.append(ServiceSpec(name(s), argv, may_finish=s == topology.SOURCE))
    return specs
