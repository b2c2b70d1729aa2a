"""The repository stands alone, and the library's text says what and why, never when.

- No tracked file points outside the repository: no path into a sibling folder, no notes
  file of the developers, no source paper by its number in a private collection, no
  work-log milestone. Physics is cited by author and year and by the project's own guide,
  `docs/physics.md`.
- Inside `rbdyn_jax/` no docstring or comment carries a date or a commit hash: how the code
  came to be is in git history, not in the code.

The patterns are built from pieces below, so that this file does not match them itself.
"""

import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "rbdyn_jax"

# Files that are not text, whatever their content (also caught by a NUL byte or bad UTF-8).
BINARY_SUFFIXES = {
    ".png",
    ".jpg",
    ".jpeg",
    ".gif",
    ".ico",
    ".pdf",
    ".woff",
    ".woff2",
    ".ttf",
    ".otf",
    ".eot",
    ".zip",
    ".gz",
    ".npz",
    ".npy",
    ".pyc",
}

_MD = ".md"
OUTSIDE = {
    "a path into a sibling folder": re.compile(re.escape(".." + "/" + "shared")),
    "the developers' physics notes": re.compile(re.escape("PHYSICS" + _MD)),
    "the developers' design notes": re.compile(re.escape("DESIGN" + _MD)),
    "the developers' style notes": re.compile(re.escape("STYLE" + _MD)),
    "a source paper by its number": re.compile("(?i)" + "seed" + " " + "00"),
    "an equation of a numbered source paper": re.compile(r"\b00[0-4] " + r"eqs?\."),
    "a work-log milestone": re.compile(r"(?i)\b" + "stop" + r" \d+"),
}

_HEX = r"(?=[0-9a-f]*\d)[0-9a-f]{7,40}"  # a hash-like token (with at least one digit)
HISTORY = {
    "a date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
    "a commit hash": re.compile(
        r"(?i)\bcommit\w*\W+(?:\w+\W+)?" + _HEX + r"\b"
        r"|\b" + _HEX + r"\W+commit"
    ),
}


def _text(path: pathlib.Path) -> str | None:
    """The file's text, or `None` for a binary (or unreadable) file."""
    if path.suffix.lower() in BINARY_SUFFIXES or not path.is_file():
        return None
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def _tracked_files() -> list[pathlib.Path]:
    """Every file git tracks in this checkout; the test is skipped outside a git checkout."""
    try:
        run = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        pytest.skip("git is not available")
    if run.returncode != 0:
        pytest.skip("not a git checkout")
    return [ROOT / name for name in run.stdout.decode("utf-8", "replace").split("\0") if name]


def _offences(files, patterns) -> list[str]:
    found = []
    for path in files:
        text = _text(path)
        if text is None:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            for what, pattern in patterns.items():
                if pattern.search(line):
                    where = path.relative_to(ROOT)
                    found.append(f"{where}:{number}: {what}: {line.strip()[:120]}")
    return found


def test_no_tracked_file_points_outside_the_repository():
    offences = _offences(_tracked_files(), OUTSIDE)
    assert not offences, (
        "cite the physics guide (docs/physics.md#…) and the source work by "
        "author and year instead:\n" + "\n".join(offences)
    )


def test_the_library_carries_no_dates_or_commit_hashes():
    files = [p for p in sorted(LIBRARY.rglob("*")) if "__pycache__" not in p.parts]
    assert files, f"no library files under {LIBRARY}"
    offences = _offences(files, HISTORY)
    assert not offences, "say what the code does and why; its history is in git:\n" + "\n".join(
        offences
    )


@pytest.mark.parametrize(
    "line, what",
    [
        ("see ../" + "shared/notes", "a path into a sibling folder"),
        ("PHYSICS" + ".md §5", "the developers' physics notes"),
        ("(DESIGN" + ".md)", "the developers' design notes"),
        ("STYLE" + ".md §8", "the developers' style notes"),
        ("Seed" + " 002's assumptions", "a source paper by its number"),
        ("000" + " eq. (11)", "an equation of a numbered source paper"),
        ("004" + " eqs. 7, 8", "an equation of a numbered source paper"),
        ("(benchmarks/README, Stop" + " 23)", "a work-log milestone"),
    ],
    ids=[
        "sibling",
        "physics-notes",
        "design-notes",
        "style-notes",
        "paper-number",
        "paper-equation",
        "paper-equations",
        "milestone",
    ],
)
def test_the_outside_patterns_catch_what_they_name(line, what):
    assert [w for w, p in OUTSIDE.items() if p.search(line)] == [what]


@pytest.mark.parametrize(
    "line, caught",
    [
        ("measured on " + "2026" + "-11-23", True),
        ("since commit " + "3c12e8b", True),
        ("(3c12e8b" + " commit)", True),
        ("commit the chunk, then mark it done", False),
        ("Mukhametzyanov (2009), eq. (11); docs/physics.md#compact-form", False),
        ("docs/physics.md#relative-motion", False),
    ],
    ids=["date", "hash-after", "hash-before", "verb", "citation", "anchor"],
)
def test_the_history_patterns_catch_dates_and_hashes(line, caught):
    assert any(p.search(line) for p in HISTORY.values()) == caught
