"""`quick-stream motion` end to end: report, trajectory, OpenCV comparison, bad input."""
import json
from pathlib import Path

import cv2
import numpy as np

from quick_stream.cli import main
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.io.sources.trajectory import matrix_to_quat, read_tum_trajectory


def run_json(capsys, *argv) -> dict:
    assert main(["motion", *argv, "--json", "-", "--quiet"]) == 0
    return json.loads(capsys.readouterr().out)


def test_synthetic_report_trajectory_and_opencv(capsys, tmp_path):
    traj = tmp_path / "path.txt"
    # the free fit (no translation prior, docs/method.md (3n)): the synthetic camera's translational shake
    # (4 mm RMS up to 8 Hz) is far beyond a hand's, and the prior takes part of it for rotation
    r = run_json(capsys, "--source", "synthetic:width=320,height=240,frames=8", "--compare-opencv",
                 "--trajectory", str(traj), "--translation-prior", "0")
    assert r["pairs"] == 7 and r["valid_pairs"] == 7
    assert set(r["timing_ms"]) == {"read", "flow", "motion"}
    ours, ocv = r["methods"]["exact se3"], r["methods"]["opencv rgbd odometry"]
    assert ours["n"] == 7 and ocv["n"] == 7
    assert ours["rot_median"] < 0.1 and ocv["rot_median"] < 0.1
    ts, poses = read_tum_trajectory(traj)
    assert len(ts) == 8
    truth = SyntheticSource(width=320, height=240, frames=8).poses()
    # anchored at the first ground-truth pose, the path tracks the truth to millimetres
    assert np.max(np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)) < 0.005
    assert r["methods"]["exact se3"]["rot_median"] < 0.01


def test_the_translation_prior_is_the_stabilizers_unless_given(capsys):
    """The product's prior by default (the stabilizer's estimator is what is measured); 0 gives the free
    fit, whose translation tracks the synthetic camera's large translational shake more closely."""
    spec = "synthetic:width=320,height=240,frames=8"
    prior = run_json(capsys, "--source", spec)
    free = run_json(capsys, "--source", spec, "--translation-prior", "0")
    assert free["methods"]["exact se3"]["trans_median"] < prior["methods"]["exact se3"]["trans_median"]


def test_table_output_names_stages_and_methods(capsys):
    assert main(["motion", "--source", "synthetic:width=320,height=240,frames=4", "--estimator", "induced",
                 "--group", "sim3"]) == 0
    out = capsys.readouterr().out
    for word in ("read", "flow", "motion", "induced sim3", "rot med"):
        assert word in out


def test_bad_source_spec_is_a_clear_error(capsys):
    assert main(["motion", "--source", "nosuch:thing"]) == 2
    assert "unknown source kind 'nosuch'" in capsys.readouterr().err
    assert main(["motion", "--source", "tum:/does/not/exist"]) == 2
    assert "/does/not/exist" in capsys.readouterr().err


def write_tum_clip(root: Path, n: int = 12) -> list[str]:
    """A TUM folder made of synthetic frames (depth 16-bit mm, ground truth included)."""
    src = SyntheticSource(width=320, height=240, frames=n, seed=5)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, dep, gt = [], [], []
    for f in src:
        t = f.timestamp_ns / 1e9
        cv2.imwrite(str(root / f"rgb/{t:.6f}.png"), f.color)
        cv2.imwrite(str(root / f"depth/{t:.6f}.png"), np.round(f.depth * 1000).astype(np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t:.6f} depth/{t:.6f}.png")
        q = matrix_to_quat(f.pose[:3, :3])
        gt.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*f.pose[:3, 3], *q)))
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(dep) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    K = src.intrinsics
    (root / "intrinsics.json").write_text(json.dumps(
        {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": K.width, "height": K.height,
         "depth_scale": 1000}))
    return rgb


def test_bad_frames_are_reported_and_the_run_goes_on(capsys, tmp_path):
    root = tmp_path / "clip"
    names = [line.split()[1] for line in write_tum_clip(root)]
    (root / names[2]).unlink()  # missing colour image
    cv2.imwrite(str(root / names[4].replace("rgb", "depth")), np.ones((10, 10), np.uint16))  # wrong size
    cv2.imwrite(str(root / names[6].replace("rgb", "depth")), np.zeros((240, 320), np.uint16))  # no valid depth
    (root / names[8]).write_bytes(b"not a png")  # unreadable
    cv2.imwrite(str(root / names[10]), np.zeros((240, 320, 3), np.uint8))  # black frame: no texture
    r = run_json(capsys, "--source", f"tum:{root}")
    bad = {b["seq"]: b["error"] for b in r["bad_frames"]}
    assert set(bad) == {2, 4, 6, 8}
    assert names[2] in bad[2] and "depth" in bad[4] and "valid" in bad[6] and names[8] in bad[8]
    # the black frame: no flow into or out of it; reached over, the flow 9->11 fitted and split across it
    # (docs/method.md 2.4), each part measured against the ground truth
    assert r["invalid_motions"] == []
    reached = {(m["seq"], m["seq_next"]): m["reason"] for m in r["fallbacks"]}
    assert set(reached) == {(9, 10), (10, 11)} and r["reached_over"] == 1
    assert all("reached over" in why and "10" in why for why in reached.values())
    assert r["motions_by_kind"] == {"fit": 7, "rotation": 0, "bridge": 0, "none": 0}
    # good pairs on either side of each gap are still measured against ground truth, by kind too
    assert r["pairs"] == 7 and r["valid_pairs"] == 7
    assert r["errors_by_kind"]["fit"]["rot_median"] < 0.1 and r["errors_by_kind"]["reached over"]["n"] == 2
    # the camera does not turn evenly across the frame (0.21 deg RMS off); the whole turn put on one side of
    # it would be 0.57 off
    assert r["errors_by_kind"]["reached over"]["rot_rmse"] < 0.35


def test_timestamps_out_of_order_are_flagged(capsys, tmp_path):
    root = tmp_path / "clip"
    lines = write_tum_clip(root, n=6)
    t3, name3 = lines[3].split()
    lines[3] = f"{float(t3) - 0.05:.6f} {name3}"  # frame 3 claims an earlier time
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    dl = (root / "depth.txt").read_text().splitlines()
    dl[3] = f"{float(t3) - 0.05:.6f} {dl[3].split()[1]}"
    (root / "depth.txt").write_text("\n".join(dl) + "\n")
    r = run_json(capsys, "--source", f"tum:{root}")
    assert [b["seq"] for b in r["bad_frames"]] == [3]
    assert "out of order" in r["bad_frames"][0]["error"]
    assert r["valid_pairs"] == 4


def test_trajectory_without_a_name_goes_under_out_numbered(capsys, tmp_path, monkeypatch):
    """The README's `--trajectory estimated.txt` wrote into the folder it ran in (the repo root): a bare
    --trajectory goes to out/trajectory.txt like stabilize's outputs, then -1, never overwritten."""
    monkeypatch.chdir(tmp_path)
    argv = ["motion", "--source", "synthetic:width=160,height=120,frames=3", "--quiet", "--trajectory"]
    assert main(argv) == 0
    assert "wrote out/trajectory.txt" in capsys.readouterr().out
    assert main(argv) == 0
    assert "wrote out/trajectory-1.txt" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["trajectory-1.txt", "trajectory.txt"]
    assert len(read_tum_trajectory(tmp_path / "out" / "trajectory.txt")[0]) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
