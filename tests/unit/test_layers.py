"""The package keeps its layers (core < stream < io < quality < bench < cli; services: core, stream, io).

tests/tools/layers.py parses every module of quick_stream/ and services/ with ``ast`` (absolute and
relative imports, at module level or inside functions) and names each import that points up a
layer; here it must find none in the repo, and must find what is planted in a copy of it.
"""
from __future__ import annotations

import shutil
import textwrap
import tomllib
from pathlib import Path

import pytest

from tests.tools.layers import check_tree, find_cycles

REPO = Path(__file__).resolve().parents[2]


def test_no_module_imports_a_higher_layer():
    found = check_tree(REPO)
    assert not found, "\n".join(map(str, found))


@pytest.fixture
def copy(tmp_path: Path) -> Path:
    """A copy of quick_stream/ and services/ to plant violations in."""
    for d in ("quick_stream", "services"):
        shutil.copytree(REPO / d, tmp_path / d, ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def plant(root: Path, rel: str, code: str) -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text() if path.exists() else ""
    path.write_text(text + "\n" + textwrap.dedent(code))


@pytest.mark.parametrize("rel, code, why", [
    ("quick_stream/core/frame.py", "def f():\n    from ..cli import main\n", "cli is above core"),
    ("quick_stream/core/render/fill.py", "from ...quality.metrics_border import scale_from_mask\n",
     "quality is above core"),
    ("quick_stream/core/stages.py", "import zenoh\n", "no zenoh"),
    ("quick_stream/core/sceneflow/lift.py", "def f():\n    import argparse\n", "no argparse"),
    ("quick_stream/core/motion_pipeline.py", "from mcap.reader import make_reader\n", "no mcap"),
    ("quick_stream/stream/runtime.py", "def f():\n    from quick_stream.cli.up_cmd import free_port\n",
     "cli is above stream"),
    ("quick_stream/io/recording.py", "from ..quality import metrics\n", "quality is above io"),
    ("quick_stream/quality/metrics.py", "from quick_stream.bench import quality\n", "bench is above quality"),
    ("quick_stream/bench/speed.py", "import quick_stream.cli.bench_cmd\n", "cli is above bench"),
    ("services/flow.py", "from quick_stream.quality.metrics import MetricsAccumulator\n",
     "a service imports only core, stream and io"),
    ("services/render.py", "def f():\n    from quick_stream.cli import argtypes\n",
     "a service imports only core, stream and io"),
    ("services/motion.py", "import services.flow\n", "never a top-level `services` package"),
    ("quick_stream/cli/up_cmd.py", "from .. import services\n", "no layer imports the services"),
    ("quick_stream/bench/pipeline.py", "import importlib\nimportlib.import_module('quick_stream.cli.up_cmd')\n",
     "cli is above bench"),
    ("quick_stream/flat.py", "import numpy\n", "a module belongs to a layer"),
])
def test_a_planted_violation_is_named(copy: Path, rel: str, code: str, why: str):
    # the copy is the repo, which has none (test_no_module_imports_a_higher_layer)
    plant(copy, rel, code)
    found = check_tree(copy)
    assert len(found) == 1 and found[0].path == rel and why in found[0].why, found


def test_same_and_lower_layers_pass(copy: Path):
    plant(copy, "quick_stream/cli/extra_cmd.py", """
        from ..bench import speed
        from ..core.frame import RGBDFrame
        from ..io.sinks import VideoSink
        from ..quality import metrics
        from ..stream import keys
    """)
    plant(copy, "quick_stream/io/extra.py", "from ..stream.wire import decode\nfrom . import sinks\n")
    plant(copy, "services/extra.py", "from quick_stream.io.sources import open_source\nfrom . import flow\n")
    assert check_tree(copy) == []


def test_no_import_cycle():
    assert find_cycles(REPO) == []


def test_a_planted_cycle_is_found_even_through_a_deferred_import(copy: Path):
    """io/foxglove <-> recording <-> recording_images was one, through a function's import."""
    plant(copy, "quick_stream/core/lie/so3.py", "def f():\n    from ..frame import Intrinsics\n")
    plant(copy, "quick_stream/core/frame.py", "from .lie import so3\n")
    assert find_cycles(copy) == [["quick_stream.core.frame", "quick_stream.core.lie.so3"]]


SOURCE_CHECKOUT_ONLY = {"quick_stream.bench", "quick_stream.io.sources.stand_in"}  # test rigs, not the product


def test_pyproject_installs_every_package_but_the_test_rigs_and_the_services_inside_the_package():
    """The product installs what a user runs: the benchmarks and the stand-in camera stay in a checkout."""
    setup = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "quick_stream").rglob("__init__.py")}
    assert SOURCE_CHECKOUT_ONLY <= on_disk
    assert set(setup["packages"]) == on_disk - SOURCE_CHECKOUT_ONLY | {"quick_stream.services"}
    assert setup["package-dir"] == {"quick_stream.services": "services"}
    assert not any(p == "services" or p.startswith("services.") for p in setup["packages"])
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    for s in ("capture", "flow", "motion", "render", "recorder"):
        assert scripts[f"quick-stream-{s}"] == f"quick_stream.services.{s}:main"


def test_without_the_test_rigs_the_product_says_where_they_are(monkeypatch, capsys):
    """An installed product (no benchmarks, no stand-in camera) refuses their commands by name."""
    import sys

    from quick_stream import cli
    from quick_stream.io.sources import SourceError, open_source

    monkeypatch.setattr(cli, "bench_installed", lambda: False)
    assert cli.main(["bench", "speed", "--pairs", "2"]) == 2
    assert "benchmarks come with a source checkout" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "quick_stream.io.sources.stand_in.oak_fake", None)  # import fails
    with pytest.raises(SourceError, match="fake= asks for the scripted stand-in camera, a test rig"):
        open_source("depthai:fake0,fake=1")


def test_the_tool_refuses_a_folder_that_is_not_a_repository_and_has_help(tmp_path: Path, capsys):
    """`/nonexistent` and `-h` were taken for the repository to check: "0 layer violation(s)", exit 0."""
    from tests.tools.layers import main

    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "nonexistent")])
    assert e.value.code == 2 and "no quick_stream package there" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["-h"])
    assert e.value.code == 0 and "usage: python -m tests.tools.layers" in capsys.readouterr().out
    assert main([]) == 0  # this repository
