"""`quick-stream stabilize` says "wrote" only for files that exist and are complete: a write that
fails (a file-size limit here; a full disk fails the same way) ends the run with exit 2 and a
message naming the flag, the file and the frame, and a run that stabilized nothing exits 1 with
one line saying why (docs/reliability.md, issue 30 rows 2 and 11)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from quick_stream.cli import main

SMALL = ["--source", "synthetic:width=320,height=240,frames=60", "--no-metrics", "--quiet"]
LIMITED = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]),) * 2); "
           "from quick_stream.cli import main; sys.exit(main(sys.argv[2:]))")


def stabilize_under_limit(limit: int, *argv: str) -> subprocess.CompletedProcess:
    """``quick-stream stabilize`` in a child whose files may not grow past ``limit`` bytes (Python
    ignores SIGXFSZ: a write past it fails with EFBIG, as ``prlimit --fsize`` makes it)."""
    return subprocess.run([sys.executable, "-c", LIMITED, str(limit), "stabilize", *argv],
                          capture_output=True, text=True, timeout=600)


def test_a_video_cut_by_the_file_size_limit_is_an_error_not_wrote(tmp_path):
    video = tmp_path / "fs.mp4"  # 60 frames, ~165 KB of mp4v: more than the limit
    done = stabilize_under_limit(100_000, *SMALL, "--output", str(video), "--report", str(tmp_path / "r.json"),
                                 "--plot", "")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "wrote" not in done.stdout
    assert f"quick-stream stabilize: --output: {video}: writing stopped at frame 0: " in done.stderr
    assert "file-size limit of 100000 bytes" in done.stderr


def test_a_report_that_cannot_be_written_leaves_no_cut_off_file(tmp_path):
    report = tmp_path / "r.json"  # ~40 KB for 60 frames
    done = stabilize_under_limit(20_000, *SMALL, "--output", "", "--report", str(report), "--plot", "")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "wrote" not in done.stdout
    assert f"quick-stream stabilize: --report: {report}: File too large" in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # neither the cut-off report nor its .part


def test_a_tum_folder_without_depth_stabilizes_nothing_and_says_why(tmp_path, shared_data, capsys):
    kitchen, clip = shared_data / "7scenes_redkitchen", tmp_path / "nodepth"
    clip.mkdir()
    shutil.copy(kitchen / "intrinsics.json", clip)
    for index in ("rgb.txt", "depth.txt"):  # the first 10 frames; their depth images are not there
        lines = (kitchen / index).read_text().splitlines()
        entries = [x for x in lines if x and not x.startswith("#")][:10]
        (clip / index).write_text("\n".join(entries) + "\n")
        if index == "rgb.txt":
            (clip / "rgb").mkdir()
            for x in entries:
                shutil.copy(kitchen / x.split()[1], clip / x.split()[1])
    out = tmp_path / "out"
    rc = main(["stabilize", "--source", f"tum:{clip}", "--output", str(out / "x.mp4"), "--report",
               str(out / "x.json"), "--plot", str(out / "x.png"), "--quiet", "--no-metrics"])
    text = capsys.readouterr()
    assert rc == 1
    assert "stabilized 0 of 10 frames" in text.out
    assert f"wrote {out / 'x.json'}" in text.out.splitlines()  # the report, which lists the bad frames: only it
    assert sorted(p.name for p in out.iterdir()) == ["x.json"]
    first = clip / "depth" / "0.000000.png"
    assert (f"quick-stream stabilize: 0 of 10 frames stabilized: depth image not found for every frame "
            f"(first: frame 0: {first}: depth image not found)") in text.err
