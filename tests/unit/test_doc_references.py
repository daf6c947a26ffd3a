"""Comments and docstrings of the product point inside the repository.

Every comment and string literal (docstrings included) of ``quick_stream/`` and ``services/`` is
read with its line breaks folded, and must not name what a reader of the repository cannot open:

* a path outside the repository. The one exception is the workplace's shared folder beside the
  checkout where code reads or runs something from it: ``../shared/data`` (the real clips, see the
  README's "Data"), ``../shared/tools/shake`` and ``../shared/tools/degrade`` (the shake and degrade
  tools the benchmarks run). Anything else there (design notes, seeds, ...) is not a reference;
* the paper's LaTeX source (``.tex``, its equation labels such as ``eq. (phi)``, its sections),
  ``transport-facts``, ``quick-method.md``, a "design note", an "issue N" of a tracker;
* a test file (``tests/....py``, optionally ``::name``) that does not exist, or lacks that name;
* a ``docs/*.md`` that does not exist, a section of it in quotes that is none of its headings (or
  bold paragraph leads), or
  an equation ``(N)`` or section ``N.M`` of docs/method.md that it does not have.

The math is cited as ``docs/method.md (N)`` or ``docs/method.md N.M`` (section).
"""
from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import pytest

from tests.tools import REPO

ROOTS = ("quick_stream", "services")

OUTSIDE = [
    (re.compile(r"\.\./shared(?!/data\b|/tools/(?:shake|degrade)\b)"),
     "a path in ../shared other than data/, tools/shake or tools/degrade"),
    (re.compile(r"\.\./(?!shared/)[\w.-]+/"), "a path outside the repository"),
    (re.compile(r"\.tex\b"), "the paper's .tex source"),
    (re.compile(r"transport-facts", re.I), "transport-facts (not in the repository)"),
    (re.compile(r"quick-method", re.I), "quick-method.md (not in the repository)"),
    (re.compile(r"\bdesign[ -]notes?\b", re.I), "a design note (not in the repository)"),
    (re.compile(r"\bissues?\s*#?\d+", re.I), "an issue of a tracker"),
    (re.compile(r"\beqs?\.\s*(?:after\s+)?\(\s*[A-Za-z_]", re.I), "an equation label of the paper's source"),
    (re.compile(r"\bequations?\s+after\s+\(\s*[A-Za-z_]", re.I), "an equation label of the paper's source"),
    (re.compile(r"\bpaper(?:'s)?,?\s+(?:the\s+)?(?:section|eqs?\.|equations?)\b", re.I), "a place in the paper"),
    (re.compile(r"\(paper\b", re.I), "a place in the paper"),
]

TEST_REF = re.compile(r"\btests/[\w/]+\.py(?:::\w+)?")
DOC_REF = re.compile(r"\bdocs/([\w-]+\.md)\b")
DOC_TITLE = re.compile(r"\bdocs/([\w-]+\.md),?\s+\"([^\"]+)\"")
METHOD_LABELS = re.compile(r"\bdocs/method\.md,?\s+((?:\(\d+[a-z]?\)(?:\s*(?:-|–|,|and|/)\s*)?)+)")
METHOD_EQUATION = re.compile(r"\bdocs/method\.md\b[^.;]*?\bequations?\s+\((\d+[a-z]?)\)")
METHOD_SECTION = re.compile(r"\bdocs/method\.md,?\s+(?:sections?\s+)?(\d+(?:\.\d+)?)(?![\d.]*\))\b")


def _texts(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every comment and string literal, whitespace folded."""
    out = []
    for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if tok.type in (tokenize.COMMENT, tokenize.STRING) or tok.type == getattr(tokenize, "FSTRING_MIDDLE", -1):
            out.append((tok.start[0], " ".join(tok.string.split())))
    return out


def _method_md() -> tuple[set[str], set[str]]:
    """docs/method.md's equation labels (at the end of an indented equation line) and section numbers."""
    text = (REPO / "docs" / "method.md").read_text()
    labels = set(re.findall(r"(?m)^ {4,}.*\s\((\d+[a-z]?)\)\s*$", text))
    sections = set(re.findall(r"(?m)^#{2,3} (\d+(?:\.\d+)?)[. ]", text))
    return labels, {s.rstrip(".") for s in sections}


def _headings(doc: str) -> list[str]:
    """The headings of a document and its bold paragraph leads (``**Overload**: ...``), lower case."""
    text = (REPO / "docs" / doc).read_text()
    return ([ln.lstrip("#").strip().lower() for ln in text.splitlines() if ln.startswith("#")]
            + [b.lower() for b in re.findall(r"\*\*([^*]+)\*\*", text)])


def problems_in(path: Path) -> list[str]:
    rel = path.relative_to(REPO).as_posix()
    labels, sections = _method_md()
    found = []
    for line, text in _texts(path):
        where = f"{rel}:{line}"
        for pattern, what in OUTSIDE:
            for m in pattern.finditer(text):
                found.append(f"{where}: {what}: {m.group(0)!r}")
        for m in TEST_REF.finditer(text):
            ref = m.group(0)
            file, _, name = ref.partition("::")
            if not (REPO / file).is_file():
                found.append(f"{where}: no such test file: {ref}")
            elif name and not re.search(rf"(?m)^\s*(?:async\s+)?(?:def|class)\s+{name}\b", (REPO / file).read_text()):
                found.append(f"{where}: {file} has no {name}")
        for m in DOC_REF.finditer(text):
            if not (REPO / "docs" / m.group(1)).is_file():
                found.append(f"{where}: no such document: docs/{m.group(1)}")
        for m in DOC_TITLE.finditer(text):
            doc, title = m.groups()
            if (REPO / "docs" / doc).is_file() and not any(title.lower() in h for h in _headings(doc)):
                found.append(f"{where}: docs/{doc} has no section {title!r}")
        cited = [lab for m in METHOD_LABELS.finditer(text) for lab in re.findall(r"\((\d+[a-z]?)\)", m.group(1))]
        cited += [m.group(1) for m in METHOD_EQUATION.finditer(text)]
        found += [f"{where}: docs/method.md has no equation ({lab})" for lab in cited if lab not in labels]
        found += [f"{where}: docs/method.md has no section {m.group(1)}" for m in METHOD_SECTION.finditer(text)
                  if m.group(1) not in sections]
    return found


def _sources() -> list[Path]:
    return sorted(p for root in ROOTS for p in (REPO / root).rglob("*.py"))


def test_comments_and_docstrings_point_inside_the_repository():
    found = [p for path in _sources() for p in problems_in(path)]
    assert found == [], "\n".join(found)


@pytest.mark.parametrize("text, bad", [
    ("see design note §3", True), ("(issue 7: bad input)", True), ("paper eq. (se3_exp)", True),
    ('(paper, "Video stabilization")', True), ("(the equation after (Lambda))", True),
    ("the paper's section 3", True), ("../shared/design/quick-method.md", True), ("see tests/test_nope.py", True),
    ("docs/method.md (99)", True), ("docs/method.md section 9.9", True), ("docs/nope.md", True),
    ("tests/unit/test_doc_references.py::no_such_test", True), ('docs/method.md, "No such section"', True),
    ("clips in ../shared/data/7scenes_redkitchen", False), ("default ../shared/tools/shake", False),
    ("default ../shared/tools/degrade", False), ("../shared/tools/degraded/x", True),
    ("docs/method.md (3e), (3f)", False), ("docs/method.md (10)-(11)", False), ("docs/method.md 5.4", False),
    ("docs/method.md section 2.3, equation (3b)", False), ('docs/reliability.md, "Bad input"', False),
    ("tests/unit/test_doc_references.py::test_comments_and_docstrings_point_inside_the_repository", False),
])
def test_the_rules(monkeypatch, text, bad):
    path = REPO / "quick_stream" / "_doc_reference_probe.py"  # relative paths are taken from the repo root
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: (f'"""{text}"""\n' if self == path
                                                                   else _read_text(self, *a, **k)))
    assert bool(problems_in(path)) is bad, problems_in(path)


_read_text = Path.read_text
