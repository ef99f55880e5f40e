"""The README's figures and file links point at files that are in the repository."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_image_and_relative_link_in_the_readme_exists():
    text = (ROOT / "README.md").read_text()
    targets = re.findall(r"!?\[[^\]]*\]\(([^)#\s]+)\)", text)
    local = [t for t in targets if not re.match(r"[a-z]+:", t)]
    assert any(t.startswith("docs/figures/") for t in local)  # the regenerated figures are shown
    missing = [t for t in local if not (ROOT / t).is_file()]
    assert not missing, missing
