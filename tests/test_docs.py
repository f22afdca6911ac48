"""The contract documents in docs/ are copies of ../shared/API.md and SCENES.md (the source of
truth CI puts beside the checkout): a copy that drifts fails here."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests import conftest
from tests.conftest import SHARED, require_shared

DOCS = Path(__file__).resolve().parents[1] / "docs"
MIRRORS = [("api.md", "API.md"), ("scenes.md", "SCENES.md")]


def mirrored(path: Path) -> str:
    """A mirror's text without its first line (the note that names the shared file) and the
    blank line after it."""
    first, _, rest = path.read_text().partition("\n")
    assert "mirrors the shared contract" in first, f"{path}: the first line must say what it mirrors"
    return rest.removeprefix("\n")


@pytest.mark.parametrize("ours, theirs", MIRRORS)
def test_contract_copies_are_in_step_with_shared(ours, theirs):
    require_shared(SHARED / theirs)
    assert mirrored(DOCS / ours) == (SHARED / theirs).read_text(), (
        f"docs/{ours} has drifted from ../shared/{theirs}: copy the shared file over it (keep the first line)"
    )


@pytest.mark.parametrize("in_ci, outcome", [(True, pytest.fail.Exception), (False, pytest.skip.Exception)])
def test_missing_shared_data_fails_in_ci_and_skips_locally(monkeypatch, tmp_path, in_ci, outcome):
    monkeypatch.setattr(conftest, "IN_CI", in_ci)
    with pytest.raises(outcome, match="needs ../shared"):
        require_shared(tmp_path / "nowhere")
    require_shared(tmp_path)  # present: nothing happens


ROOT = DOCS.parent
#: [text](target): the target up to a space, a closing parenthesis or an anchor
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)\s]*)?\)")


def markdown_files() -> list[Path]:
    skip = {".venv", ".git", "node_modules"}
    return sorted(p for p in ROOT.rglob("*.md") if not skip & set(p.relative_to(ROOT).parts))


def test_relative_links_in_markdown_resolve():
    """Every link to a file of this repository names one that a clean checkout has: a report's
    log that .gitignore kept out of the commit would fail here, not in a reader's browser."""
    broken = []
    for md in markdown_files():
        for target in LINK.findall(md.read_text()):
            if "://" in target or target.startswith(("mailto:", "/")):
                continue
            if not (md.parent / target).exists():
                broken.append(f"{md.relative_to(ROOT)} -> {target}")
    assert not broken, "broken links:\n" + "\n".join(broken)
