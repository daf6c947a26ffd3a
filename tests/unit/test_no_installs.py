"""The product installs nothing: no package manager is run from quick_stream/ or services/.

What a benchmark or source lacks is named with the command that installs it (e.g.
``bench/ffmpeg_baselines.INSTALL_COMMAND``, printed in the table row), never run: a command's argv
(a list or tuple of strings) never starts a package manager, and nothing goes through a shell
(``os.system``, ``shell=True``) where such a command could hide in a string.
"""
from __future__ import annotations

import ast
from pathlib import Path

from tests.tools import REPO

INSTALLERS = {"apt", "apt-get", "aptitude", "dpkg", "yum", "dnf", "brew", "snap", "sudo", "conda", "mamba"}
PIP = {"pip", "pip3", "uv", "pipx"}


def _strings(node: ast.AST) -> list[str]:
    return [e.value for e in getattr(node, "elts", []) if isinstance(e, ast.Constant) and isinstance(e.value, str)]


def problems_in(path: Path) -> list[str]:
    rel = path.relative_to(REPO).as_posix()
    found = []
    for node in ast.walk(ast.parse(path.read_text(), rel)):
        if isinstance(node, (ast.List, ast.Tuple)):
            words = [w.rsplit("/", 1)[-1] for w in _strings(node)]
            if INSTALLERS & set(words) or (PIP & set(words) and "install" in words):
                found.append(f"{rel}:{node.lineno}: runs a package manager: {_strings(node)}")
        elif isinstance(node, ast.Call):
            name = ast.unparse(node.func)
            if name in ("os.system", "os.popen"):
                found.append(f"{rel}:{node.lineno}: {name} (a shell command)")
            if any(k.arg == "shell" and not (isinstance(k.value, ast.Constant) and k.value.value is False)
                   for k in node.keywords):
                found.append(f"{rel}:{node.lineno}: {name}(..., shell=...)")
    return found


def test_nothing_installs_anything():
    found = [p for root in ("quick_stream", "services") for path in sorted((REPO / root).rglob("*.py"))
             for p in problems_in(path)]
    assert found == [], "\n".join(found)


def test_the_rule(monkeypatch):
    probe = REPO / "quick_stream" / "_install_probe.py"
    cases = {'subprocess.run(["sudo", "apt-get", "install", "-y", "ffmpeg"])': True,
             'subprocess.run([sys.executable, "-m", "pip", "install", "vidstab"])': True,
             'os.system("apt-get install ffmpeg")': True, 'subprocess.run(cmd, shell=True)': True,
             'INSTALL = "sudo apt-get install ffmpeg"  # printed, not run': False,
             'subprocess.run([ffmpeg, "-hide_banner", "-filters"])': False}
    real = Path.read_text
    for code, bad in cases.items():
        monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: code if self == probe else real(self, *a, **k))
        assert bool(problems_in(probe)) is bad, code
