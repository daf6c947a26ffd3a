"""What the commands write, and where: outputs never overwritten silently (default names numbered,
named files refused without ``--force``), outputs that cannot be created refused before any work,
``--json FILE`` / ``--json -`` the same everywhere, ``evaluate tum:PATH``, ``recover`` leaving no
file behind, progress on stderr. Exit codes and messages, never a traceback.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from quick_stream.cli import main
from quick_stream.cli.progress import Progress, heartbeat
from quick_stream.io.recording import Recorder
from quick_stream.io.sources import open_source
from quick_stream.stream import argtypes as at
from quick_stream.stream.keys import key
from quick_stream.stream.wire import encode_frame

SMALL = ["--source", "synthetic:frames=12,width=64,height=48", "--no-metrics", "--quiet"]
LINUX_PROC = Path("/proc/self").exists()


def run(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse's own errors
        code = e.code if isinstance(e.code, int) else 1
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
    return code, out.out, out.err


def small_recording(path: Path, frames: int = 3) -> Path:
    with Recorder(path) as rec:
        for f in open_source(f"synthetic:frames={frames},width=64,height=48"):
            rec.write(key("cam0", "frame"), encode_frame(f, "cam0", color="raw", depth="raw", depth_scale=1000.0),
                      log_time_ns=10**9 + f.timestamp_ns)
    return path


# ---------------------------------------------------------------- never overwritten silently

def test_stabilize_numbers_its_default_outputs_together(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run(capsys, "stabilize", *SMALL)[0] == 0
    (tmp_path / "out" / "path-1.png").write_bytes(b"an earlier plot")  # one of the set taken: all move on
    code, out, _ = run(capsys, "stabilize", *SMALL)
    assert code == 0
    assert "wrote out/stabilized-2.mp4, out/report-2.json, out/path-2.png" in out
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == ["path-1.png", "path-2.png", "path.png", "report-2.json", "report.json",
                     "stabilized-2.mp4", "stabilized.mp4"]
    assert (tmp_path / "out" / "path-1.png").read_bytes() == b"an earlier plot"


def test_a_named_output_that_exists_is_refused_unless_force(tmp_path, capsys):
    video = tmp_path / "mine.mp4"
    video.write_bytes(b"keep me")
    code, out, err = run(capsys, "stabilize", *SMALL, "--output", str(video), "--report", "", "--plot", "")
    assert code == 2 and f"--output {video}: exists" in err and "--force" in err and not out
    assert video.read_bytes() == b"keep me"
    code, out, _ = run(capsys, "stabilize", *SMALL, "--output", str(video), "--report", "", "--plot", "", "--force")
    assert code == 0 and video.stat().st_size > 1000


@pytest.mark.parametrize("argv", [
    ["motion", "--source", "synthetic:frames=3,width=64,height=48", "--trajectory", "{f}"],
    ["motion", "--source", "synthetic:frames=3,width=64,height=48", "--json", "{f}"],
    ["evaluate", "tum:{d}", "--json", "{f}"],
    ["recording-stats", "{rec}", "--json", "{f}"],
    ["acl", "--output", "{f}"],
    ["bench", "path", "--segments", "1", "--json", "{f}"],
])
def test_every_file_output_is_refused_when_it_exists(argv, tmp_path, capsys):
    existing = tmp_path / "existing.txt"
    existing.write_text("keep me")
    rec = small_recording(tmp_path / "rec.mcap")
    argv = [a.format(f=existing, d=tmp_path, rec=rec) for a in argv]
    code, _, err = run(capsys, *argv)
    assert code == 2 and str(existing) in err and "exists" in err and "--force" in err, err
    assert existing.read_text() == "keep me"


def test_png_folder_holding_frames_is_refused_unless_force(tmp_path, capsys):
    png = tmp_path / "png"
    png.mkdir()
    (png / "000000.png").write_bytes(b"an earlier frame")
    argv = ["stabilize", *SMALL, "--output", "", "--report", "", "--plot", "", "--png", str(png)]
    code, _, err = run(capsys, *argv)
    assert code == 2 and f"--png {png}: already holds *.png files" in err
    assert run(capsys, *argv, "--force")[0] == 0 and len(list(png.glob("*.png"))) == 12


@pytest.mark.parametrize("codec,video", [("mjpeg", "stabilized.avi"), ("mp4v", "stabilized.mp4")])
def test_up_numbers_its_video_like_its_recording(tmp_path, capsys, monkeypatch, codec, video):
    """A second ``up`` in the same folder hands render out/stabilized-1.avi, the recorder
    recording-1.mcap and the services fresh logs in out/logs-1 (they were appended to out/logs, whose
    status.json was overwritten); the earlier run's files stay. The video's container is its codec's: Motion
    JPEG in .avi (its own tag, no OpenCV notice), mp4v in .mp4 (it was .mp4 for both: Motion JPEG under
    the tag 'mp4v' after OpenCV's "tag 'MJPG' is not supported" on every run)."""
    from quick_stream.stream import launcher

    class Started(BaseException):
        pass

    specs = {}

    def capture(self, children, logs):
        specs.update({s.name: s.argv for s in children}, logs=logs)
        raise Started

    monkeypatch.setattr(launcher.Supervisor, "__init__", capture)
    out = tmp_path / "out"
    out.mkdir()
    stem, suffix = video.split(".")
    (out / video).write_bytes(b"earlier")
    (out / "recording.mcap").write_bytes(b"earlier")
    (out / "logs").mkdir()
    for name in ("status.json", "capture.log", "settings.toml"):
        (out / "logs" / name).write_text("earlier")
    with pytest.raises(Started):
        main(["up", "--out", str(out), "--video-codec", codec])
    render, recorder = specs["render"], specs["recorder"]
    assert render[render.index("--output") + 1] == str(out / f"{stem}-1.{suffix}")
    assert render[render.index("--video-codec") + 1] == codec
    assert recorder[recorder.index("--output") + 1] == str(out / "recording-1.mcap")
    assert (out / video).read_bytes() == b"earlier"
    assert specs["logs"] == out / "logs-1"
    settings = render[render.index("--settings") + 1]
    assert settings == str(out / "logs-1" / "settings.toml") and Path(settings).is_file()
    assert all(f.read_text() == "earlier" for f in (out / "logs").iterdir())
    assert sorted(f.name for f in (out / "logs").iterdir()) == ["capture.log", "settings.toml", "status.json"]


def test_a_runs_files_share_one_number(tmp_path):
    """The video, the recording and the logs of one run go together: a folder where only the recording
    was numbered on (the video was .mp4 then, or a recording split) still gets one number for all."""
    from quick_stream.cli.up_run import run_paths

    assert run_paths(tmp_path, "mjpeg") == (tmp_path / "stabilized.avi", tmp_path / "recording.mcap",
                                            tmp_path / "logs")
    for name in ("stabilized.mp4", "recording.mcap", "recording-1.mcap", "logs"):
        (tmp_path / name).touch()
    assert run_paths(tmp_path, "mjpeg") == (tmp_path / "stabilized-2.avi", tmp_path / "recording-2.mcap",
                                            tmp_path / "logs-2")


# ---------------------------------------------------------------- outputs that cannot be created

@pytest.mark.skipif(not LINUX_PROC, reason="needs /proc, where no file can be created")
@pytest.mark.parametrize("argv, flag, path", [
    (["stabilize", *SMALL, "--output", "/proc/x.mp4"], "--output", "/proc/x.mp4"),
    (["stabilize", *SMALL, "--report", "/proc/r.json"], "--report", "/proc/r.json"),
    (["up", "--out", "/proc/foo"], "--out", "/proc/foo"),
    (["up", "--png", "/proc/foo/png"], "--png", "/proc/foo/png"),
    (["motion", "--json", "/proc/m.json"], "--json", "/proc/m.json"),
    (["recover", "rec.mcap", "/proc/r.mcap"], "DST", "/proc/r.mcap"),
    (["bench", "pipeline", "--out", "/proc/bench"], "--out", "/proc/bench"),
])
def test_an_output_that_cannot_be_created_is_refused_before_any_work(argv, flag, path, tmp_path, capsys, monkeypatch):
    from quick_stream.bench import pipeline
    from quick_stream.stream import launcher

    def reached(*_a, **_k):
        raise AssertionError("work started")

    monkeypatch.setattr(launcher.Supervisor, "start", reached)
    monkeypatch.setattr(pipeline, "main", reached)
    monkeypatch.chdir(tmp_path)
    small_recording(tmp_path / "rec.mcap")
    code, out, err = run(capsys, *argv)
    assert code == 2 and f"{flag} {path}: cannot create files in /proc" in err, err
    assert "stabilized" not in out


def test_output_probe_names_flag_and_path(tmp_path):
    """Permission bits are not trusted (root passes them): the check creates and removes a file."""
    at.check_output(at.OutputPath(str(tmp_path / "new" / "deeper" / "v.mp4"), "--output"))
    assert not (tmp_path / "new").exists() and not list(tmp_path.iterdir())  # nothing left behind
    if LINUX_PROC:
        with pytest.raises(ValueError, match=r"^--out /proc/q/r: cannot create files in /proc"):
            at.check_output(at.OutputPath("/proc/q/r", "--out", directory=True))


# ---------------------------------------------------------------- --json FILE, --json -

def test_json_to_stdout_is_the_only_thing_there(capsys):
    code, out, err = run(capsys, "motion", "--source", "synthetic:frames=4,width=64,height=48", "--json", "-")
    assert code == 0
    assert json.loads(out)["pairs"] == 3  # all of stdout is one JSON document
    assert "relative pose error" in err  # the text report went to stderr


def test_json_to_a_file_keeps_the_text_report(tmp_path, capsys):
    dest = tmp_path / "sub" / "m.json"
    code, out, _ = run(capsys, "motion", "--source", "synthetic:frames=4,width=64,height=48", "--json", str(dest))
    assert code == 0 and "relative pose error" in out
    assert json.loads(dest.read_text())["pairs"] == 3


def test_json_conventions_in_bench_and_recording_stats(tmp_path, capsys):
    code, out, err = run(capsys, "bench", "path", "--segments", "1", "--json", "-")
    assert code == 0 and set(json.loads(out)) == {"ga3", "sa3", "se3", "sim3"} and "ms/frame" in err.replace(" ", "")
    rec = small_recording(tmp_path / "rec.mcap")
    code, out, _ = run(capsys, "recording-stats", str(rec), "--json", "-")
    assert code == 0 and json.loads(out)[0]["frames"] == 3


def test_json_without_a_value_is_a_usage_error(capsys):
    code, _, err = run(capsys, "motion", "--json")
    assert code == 2 and "--json" in err and "expected one argument" in err


# ---------------------------------------------------------------- evaluate reads tum:PATH

def tum_clip(root: Path, frames: int = 14) -> Path:
    from tests.unit.test_cli_motion import write_tum_clip  # a TUM folder of synthetic frames

    write_tum_clip(root, frames)
    return root


@pytest.mark.parametrize("prefix", ["tum:", ""])
def test_evaluate_takes_tum_path_and_the_bare_folder(prefix, tmp_path, capsys):
    root = tum_clip(tmp_path / "clip")
    dest = tmp_path / "e.json"
    code, out, _ = run(capsys, "evaluate", f"{prefix}{root}", "-k", "1", "-l", "6", "--groups", "se3",
                       "--json", str(dest))
    assert code == 0 and "| se3 |" in out and json.loads(dest.read_text())["folder"] == str(root)


@pytest.mark.parametrize("clip, says", [
    ("mcap:rec.mcap", "tum:PATH"), ("synthetic", None), ("synthetic:frames=3", "tum:PATH"),
    ("tum:x,count=3", "without options"), ("tum:", "empty"),
])
def test_evaluate_refuses_other_clips_by_name(clip, says, capsys):
    code, _, err = run(capsys, "evaluate", clip)
    assert code == 2 and (says is None or says in err), err


# ---------------------------------------------------------------- recover

def test_recover_never_overwrites_and_leaves_nothing_on_failure(tmp_path, capsys):
    rec = small_recording(tmp_path / "rec.mcap")
    assert run(capsys, "recover", str(rec))[0] == 0
    code, out, _ = run(capsys, "recover", str(rec))
    assert code == 0 and str(tmp_path / "rec.recovered-1.mcap") in out  # numbered, the first kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap", "rec.recovered-1.mcap", "rec.recovered.mcap"]
    dst = tmp_path / "mine.mcap"
    dst.write_bytes(b"keep me")
    code, _, err = run(capsys, "recover", str(rec), str(dst))
    assert code == 2 and f"DST {dst}: exists" in err and "--force" in err and dst.read_bytes() == b"keep me"
    assert run(capsys, "recover", str(rec), str(dst), "--force")[0] == 0 and dst.stat().st_size > 1000
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an MCAP file")
    code, _, err = run(capsys, "recover", str(junk))
    assert code == 2 and "junk.mcap" in err
    assert not list(tmp_path.glob("junk.recovered*")) and not list(tmp_path.glob("*.part"))  # no empty file


# ---------------------------------------------------------------- progress on stderr

class Tty:
    def __init__(self, tty: bool) -> None:
        self.text, self.tty = "", tty

    def write(self, s: str) -> None:
        self.text += s

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self.tty


def test_progress_is_throttled_and_shows_the_last(monkeypatch):
    now = [100.0]
    monkeypatch.setattr("quick_stream.cli.progress.time.monotonic", lambda: now[0])
    s = Tty(False)
    p = Progress("quick-stream bench x", stream=s)
    for i in range(1, 31):  # 30 items, 8 a second
        p(f"item {i}/30")
        now[0] += 0.125
    p("phase two", force=True)
    p("item 1/5")
    p.close()
    lines = s.text.splitlines()
    assert lines[0] == "quick-stream bench x: [    0.0 s] item 1/30"
    assert [ln.split("] ")[1] for ln in lines] == ["item 1/30", "item 9/30", "item 17/30", "item 25/30", "phase two",
                                                     "item 1/5"]
    t = Tty(True)
    with Progress("p", stream=t) as q:
        q("a")
    assert t.text.startswith("\rp: [") and t.text.endswith("a\x1b[K\n")  # a terminal: one line, rewritten


def test_heartbeat_says_it_is_working():
    s = Tty(False)
    with heartbeat("quick-stream rerun", "re-running flow", after_s=0.05, every_s=0.05, stream=s):
        import time

        time.sleep(0.3)
    assert s.text.count("re-running flow") >= 2 and s.text.startswith("quick-stream rerun: [")
    quiet = Tty(False)
    with heartbeat("x", "never shown", after_s=5.0, stream=quiet):
        pass
    assert quiet.text == ""


@pytest.mark.parametrize("argv, says", [
    (["bench", "speed", "--pairs", "3", "--width", "64", "--height", "48"], "pair 3/3"),
    (["bench", "path", "--segments", "2"], "ga3: segment 1/2"),
    (["motion", "--source", "synthetic:frames=4,width=64,height=48"], "4/4 frames"),
])
def test_long_commands_report_progress_on_stderr(argv, says, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stderr", sys.stderr)  # capsys's
    code, out, err = run(capsys, *argv)
    assert code == 0 and says in err and says not in out, err
