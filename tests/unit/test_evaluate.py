"""`quick-stream evaluate` and the quality benchmark plumbing on small inputs."""
import json

import pytest

from quick_stream.cli import main
from quick_stream.quality.evaluate import EvaluateParams, pick_starts

from tests.unit.test_cli_motion import write_tum_clip


def test_subsequence_starts_are_seeded_and_in_range():
    p = EvaluateParams(subsequences=20, length=30, seed=3)
    a, b = pick_starts(250, p), pick_starts(250, p)
    assert a == b and len(a) == 20 and min(a) >= 0 and max(a) <= 220
    assert pick_starts(250, EvaluateParams(seed=4)) != a
    with pytest.raises(ValueError, match="fewer than"):
        pick_starts(10, p)


def test_evaluate_command_prints_markdown_and_writes_json(tmp_path, capsys):
    root = tmp_path / "clip"
    write_tum_clip(root, n=24)
    out = tmp_path / "eval.json"
    rc = main(["evaluate", str(root), "-k", "2", "-l", "12", "--groups", "se3,sim3", "--json", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "| se3 |" in text and "| sim3 |" in text and "cropping" in text
    r = json.loads(out.read_text())
    assert len(r["runs"]) == 4 and set(r["table"]) == {"se3", "sim3"}
    for row in r["table"].values():
        assert row["failures"] == 0
        assert 0.8 < row["cropping"] <= 1.05 and row["distortion"] > 0.9
        assert row["jitter_px"] < row["input_jitter_px"]


def test_evaluate_rejects_bad_arguments(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path / "missing"), "-k", "1"]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path), "--groups", "so3"]) == 2
