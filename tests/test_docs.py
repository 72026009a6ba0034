"""The Markdown pages: readable text (UTF-8, no control characters pasted from a terminal) whose
relative links lead to files of the repository."""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pages() -> list[Path]:
    try:
        listed = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True, check=True)
        names = listed.stdout.split()
    except (OSError, subprocess.CalledProcessError):  # not a git checkout (an sdist): the files on disk
        names = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*.md") if ".venv" not in p.parts]
    return [ROOT / name for name in names if (ROOT / name).is_file()]


PAGES = _pages()
LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_page_is_clean_text_with_working_links(page):
    text = page.read_bytes().decode("utf-8")  # raises on anything but UTF-8
    bad = [(n + 1, repr(ch)) for n, line in enumerate(text.splitlines()) for ch in line
           if ord(ch) < 32 and ch != "\t"]
    assert not bad, f"{page.relative_to(ROOT)}: control characters at lines {bad[:5]}"
    broken = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue  # a web address or an anchor of the page
        path = target.split("#", 1)[0]
        if path and not (page.parent / path).exists():
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files: {broken}"
