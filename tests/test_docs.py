"""The docs hold together: every doc a file cites exists, every relative link in a doc
resolves, the README stays a short user's page (no commit hashes, no dates: those go to
docs/history.md and docs/notes/), and the reference pages under docs/ stay short."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Where doc paths are cited: code, settings, scripts, the docs and the README.
CITING = ("src", "conf", "scripts", "docs")
README = ROOT / "README.md"

# `docs/....md` cited by its path from the repository root (an `#anchor` after it is not part
# of the match). Not when it continues a longer path (`../docs/x.md`, a URL): relative links
# are checked from the citing file's folder below.
DOC_PATH = re.compile(r"(?<![\w./-])docs/[\w./-]+\.md")
# [text](target) and ![alt](target), an optional "title" after the target.
LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")

# A commit hash: 7 to 40 lowercase hex digits standing alone, with at least one digit and one
# letter (so neither a plain number nor a hex-letter word such as "facade" is one).
HEX_WORD = re.compile(r"\b[0-9a-f]{7,40}\b")
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")

README_MAX_LINES = 160
DOC_MAX_LINES = 600


def _text(path: Path) -> str | None:
    data = path.read_bytes()
    if b"\0" in data:
        return None  # binary
    return data.decode("utf-8", errors="replace")


def _citing_files() -> list[Path]:
    out = [README]
    for top in CITING:
        for p in sorted((ROOT / top).rglob("*")):
            if p.is_file() and "__pycache__" not in p.parts and ".egg-info" not in str(p):
                out.append(p)
    return out


def _docs() -> list[Path]:
    return [README] + sorted((ROOT / "docs").rglob("*.md"))


def cited_doc_paths(text: str) -> set[str]:
    """``docs/....md`` paths a text cites (from the repository root)."""
    return set(DOC_PATH.findall(text))


def relative_links(markdown: str) -> list[str]:
    """Targets of the Markdown links and images of ``markdown`` that are relative paths
    (no URL, no bare ``#anchor``), with any ``#anchor`` or ``?query`` cut off; links inside
    code (fenced blocks, inline code) are not links."""
    prose = INLINE_CODE.sub("", FENCE.sub("", markdown))
    out = []
    for target in LINK.findall(prose):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith(("#", "/")):
            continue  # a URL (http:, mailto:, ...), an anchor in the same page, or an absolute path
        path = re.split(r"[#?]", target, maxsplit=1)[0]
        if path:
            out.append(path)
    return out


def commit_hashes(text: str) -> list[str]:
    return [w for w in HEX_WORD.findall(text) if re.search(r"\d", w) and re.search(r"[a-f]", w)]


def dates(text: str) -> list[str]:
    return DATE.findall(text)


def readme_problems(text: str) -> list[str]:
    """Why ``text`` is not a user's README: too long, a commit hash, a date."""
    problems = []
    n = len(text.splitlines())
    if n > README_MAX_LINES:
        problems.append(f"{n} lines (at most {README_MAX_LINES})")
    if hashes := commit_hashes(text):
        problems.append(f"commit hashes {sorted(set(hashes))[:10]} (move them to docs/history.md)")
    if found := dates(text):
        problems.append(f"dates {sorted(set(found))[:10]} (move them to docs/history.md)")
    return problems


def test_cited_doc_paths_exist():
    missing = []
    for f in _citing_files():
        text = _text(f)
        if text is None:
            continue
        for cited in sorted(cited_doc_paths(text)):
            if not (ROOT / cited).is_file():
                missing.append(f"{f.relative_to(ROOT)}: {cited}")
    assert not missing, "cited docs that do not exist:\n" + "\n".join(missing)


def test_relative_links_in_docs_resolve():
    broken = []
    for f in _docs():
        for target in relative_links(f.read_text()):
            if not (f.parent / target).exists():
                broken.append(f"{f.relative_to(ROOT)}: ({target})")
    assert not broken, "relative links that resolve to nothing:\n" + "\n".join(broken)


def test_readme_is_a_short_users_page():
    problems = readme_problems(README.read_text())
    assert not problems, "README.md: " + "; ".join(problems)


def test_readme_starts_with_the_two_setup_commands():
    text = README.read_text()
    for command in ("bash scripts/main.sh", "bash scripts/test.sh"):
        assert command in text, f"README.md: `{command}` missing"


def test_reference_pages_are_short():
    notes, history = ROOT / "docs" / "notes", ROOT / "docs" / "history.md"
    long = []
    for f in sorted((ROOT / "docs").rglob("*")):
        if not f.is_file() or f == history or notes in f.parents or _text(f) is None:
            continue
        n = len(f.read_text().splitlines())
        if n > DOC_MAX_LINES:
            long.append(f"{f.relative_to(ROOT)}: {n} lines")
    assert not long, (f"reference pages over {DOC_MAX_LINES} lines (move dated studies to docs/notes/):\n"
                      + "\n".join(long))


# The checks themselves: each must be able to fail.
@pytest.mark.parametrize("text, problem", [
    ("\n" * 200, "lines"),
    ("measured at fb0aaa6 on the 2-core machine", "commit hashes"),
    ("the ff2cb23 repro", "commit hashes"),
    ("(2026-11-29, every stage)", "dates"),
])
def test_readme_check_catches(text, problem):
    assert any(problem in p for p in readme_problems(text))


@pytest.mark.parametrize("text", [
    "a facade of 1234567 bytes, decade, 800x600, 1e-4 px, float32, sha256sum, 0.000113",
    "torch==2.13.0, cameras_sphere.npz, world_mat_i, scan24, 3DGS, 2DGS, views 23/24/33",
])
def test_readme_check_spares_words_and_numbers(text):
    assert readme_problems(text) == []


def test_link_and_citation_parsing():
    md = ("See [mesh](docs/mesh.md#options), ![img](../img/a.png \"t\"), [web](https://x.org/docs/a.md), "
          "[here](#top), `[code](nope.md)`, docs/inputs.md#units and ../docs/notes/x.md.\n"
          "```\n[fenced](nope2.md)\n```\n")
    assert relative_links(md) == ["docs/mesh.md", "../img/a.png"]
    assert cited_doc_paths(md) == {"docs/mesh.md", "docs/inputs.md"}
