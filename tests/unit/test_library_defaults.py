"""The library's defaults are the product's: ``Stabilizer()`` is ``quick-stream stabilize`` with no flags
(quick_stream/core/params.py), and the user-facing settings' defaults are ``StabilizerParams()``'s."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from quick_stream.cli import main as cli_main
from quick_stream.core.params import USER_SETTINGS, StabilizerParams, user_defaults, with_user_settings
from quick_stream.core.render.framing import FramingParams
from quick_stream.io.sources import open_source
from quick_stream.io.stabilizer_flags import FLAG_DEFAULTS, FLAGS, default_settings

FRAMES = 40  # more than one 30-frame window: a release, a look-ahead re-planned, the end


def test_the_library_stabilizer_gives_what_stabilize_gives_with_default_flags(shared_data, tmp_path, monkeypatch):
    from quick_stream.core import Stabilizer  # the library's entry point, as a user writes it

    spec = f"tum:{shared_data / '7scenes_redkitchen'}"
    st = Stabilizer()
    lib: dict[int, np.ndarray] = {}
    for i, frame in enumerate(open_source(spec)):
        if i == FRAMES:
            break
        lib.update((sf.seq, sf.image) for sf in st.push(frame))
    lib.update((sf.seq, sf.image) for sf in st.finish())

    monkeypatch.chdir(tmp_path)  # the command's default outputs (out/...) land here
    assert cli_main(["stabilize", "--source", spec, "--frames", str(FRAMES), "--png", "png", "--no-metrics",
                     "--quiet"]) == 0
    cmd = {int(p.stem): cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in (tmp_path / "png").glob("*.png")}
    assert sorted(lib) == sorted(cmd) == list(range(FRAMES))
    assert [s for s in lib if not np.array_equal(lib[s], cmd[s])] == []
    assert st.params == default_settings() == StabilizerParams()


def test_the_flags_defaults_are_the_parameter_trees():
    assert with_user_settings(StabilizerParams(), user_defaults()) == StabilizerParams()
    assert FLAG_DEFAULTS == user_defaults() and FLAGS == USER_SETTINGS
    p = StabilizerParams()
    # the product frames with the planned zoom, bounded by the crop budget; the renderer alone shows black
    assert (p.framing.mode, p.framing.max_zoom) == ("auto", p.planner.budget.max_zoom)
    assert FramingParams().mode == "black"


def test_one_setting_sets_every_parameter_it_couples():
    p = with_user_settings(StabilizerParams(), {"group": "sim3", "max_zoom": 1.3, "latency": "low"})
    assert p.motion.group == p.planner.group == "sim3"
    assert p.planner.budget.max_zoom == p.framing.max_zoom == 1.3
    assert (p.planner.keyframes.interval, p.planner.lookahead, p.planner.smoothness) == (15, 10, 3000.0)
    # no crop budget: the framing keeps the renderer's own bound
    assert with_user_settings(p, {"max_zoom": 0}).framing.max_zoom == FramingParams.max_zoom
    with pytest.raises(ValueError, match=r"unknown settings \['zoom'\].*'max_zoom'"):
        with_user_settings(p, {"zoom": 1.2})
