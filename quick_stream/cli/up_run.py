"""One run of ``quick-stream up``: its files (a fresh numbered set in ``--out``: :class:`RunPaths`), the
settings file every service reads, the router's TLS config, and its processes' command lines
(:func:`service_specs`, built with the stream's own builder, :mod:`quick_stream.stream.stream_specs`)."""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from ..io.settings_file import settings_toml
from ..io.sinks import VIDEO_SUFFIX
from ..stream import argtypes as at, topology
from ..stream.launcher import ServiceSpec, router_spec
from ..stream.stream_specs import stream_specs
from .up_report import SERVICES


def tls_party(args: argparse.Namespace, name: str) -> tuple[str, str]:
    """(--tls-dir, --tls-name) of party ``name`` (router, monitor, or a service of ``args.stream``) in the
    folder make-certs.sh wrote."""
    d = Path(args.tls_dir)
    return (str(d / name), name) if name in ("router", "monitor") else (str(d / args.stream / name), name)


def check_tls(args: argparse.Namespace) -> None:
    """ValueError naming what is missing when ``--tls-dir`` lacks a certificate ``up`` needs."""
    if args.router_config and not args.tls_dir:
        raise ValueError("--router-config goes with --tls-dir")
    if not args.tls_dir:
        return
    from ..stream.transport import tls_settings

    names = ["router", "monitor", *(s for s in SERVICES if s != "recorder" or not args.no_record)]
    for name in names:
        d, n = tls_party(args, name)
        try:
            tls_settings(d, n, "client")
        except ValueError as e:
            raise ValueError(f"--tls-dir {args.tls_dir}: {e} (deploy/tls/make-certs.sh --streams {args.stream} "
                             f"{args.tls_dir})") from None
    if args.router_config and not Path(args.router_config).is_file():
        raise ValueError(f"--router-config {args.router_config}: no such file")


def service_specs(args: argparse.Namespace, endpoint: str, paths: RunPaths) -> list[ServiceSpec]:
    """Router first, then the services in start order, each with the zenoh flags to reach the router
    (with ``--tls-dir``: as TLS clients, each with its own certificate)."""
    tls = bool(getattr(args, "tls_dir", None))

    def z(name: str) -> list[str]:
        flags = ["-e", endpoint, "--no-multicast-scouting", "--stream", args.stream]
        if tls:
            d, n = tls_party(args, name)
            flags = ["-m", "client", *flags, "--tls-dir", d, "--tls-name", n]
        return flags

    st = ["--settings", str(paths.settings)]
    router = ["-m", "quick_stream", "router", "-l", endpoint, "--no-multicast-scouting"]
    if tls:
        d, n = tls_party(args, "router")
        router += ["-c", str(paths.router_config), "--tls-dir", d, "--tls-name", n]
    cap = ["--source", args.source, "--pace", args.pace, "--color", args.color]
    if args.frames is not None:
        cap += ["--frames", str(args.frames)]
    if args.fps is not None:
        cap += ["--fps", str(args.fps)]
    own = {"recorder": [*st, "--output", str(paths.recording)], "flow": st, "motion": st,
           "render": [*st, "--output", str(paths.video),
                      "--video-codec", args.video_codec] + (["--png", args.png] if args.png else []),
           "capture": cap}
    run = [s for s in topology.SERVICES if s != topology.RECORDER or not args.no_record]
    return [router_spec(router), *stream_specs(z, own, run=run)]


def video_name(out: Path, codec: str) -> Path:
    return out / f"stabilized{VIDEO_SUFFIX[codec]}"  # the codec's own container


def run_paths(out: Path, codec: str) -> tuple[Path, Path, Path]:
    """This run's video, recording and logs folder in ``out``: never an earlier run's, all with the first
    number free for every one of them (``stabilized-1.avi``, ``recording-1.mcap``, ``logs-1``), so a run's
    files go together and its logs and status.json are its own (they were appended to and overwritten)."""
    paths = [video_name(out, codec), out / "recording.mcap", out / "logs"]
    n = at.first_free(paths)
    video, recording, logs = (Path(at.numbered_path(p, n)) for p in paths)
    return video, recording, logs


@dataclass(frozen=True)
class RunPaths:
    """Where one run of ``up`` writes: its video, recording and logs folder (:func:`run_paths`), the one
    settings file every service reads, and the router's config (``--router-config``, or the one the run
    wrote for ``--tls-dir``; None: the router's defaults)."""

    video: Path
    recording: Path
    logs: Path
    settings: Path
    router_config: Path | None

    @property
    def status(self) -> Path:
        return self.logs / "status.json"


def prepare_run(args: argparse.Namespace, params, out: Path) -> RunPaths:
    """The output folder, this run's fresh file names, the settings file (and the router's TLS config)."""
    out.mkdir(parents=True, exist_ok=True)
    video, recording, logs = run_paths(out, args.video_codec)
    # one settings file for every service (and the recording's settings record)
    logs.mkdir()
    settings = logs / "settings.toml"
    settings.write_text(settings_toml(params, f"settings of {recording.name} (quick-stream up)"))
    router_config = Path(args.router_config) if args.router_config else None
    if args.tls_dir and router_config is None:
        from ..stream.acl import router_config_text

        router_config = logs / "router-tls.json5"
        router_config.write_text(router_config_text([args.stream]))
    return RunPaths(video, recording, logs, settings, router_config)
