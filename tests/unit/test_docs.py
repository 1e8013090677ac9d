"""The documentation is self-contained: its links stay inside the repository and resolve.

Also checks that the parameter table of docs/spec/auction_env.md agrees with ``AuctionParams``.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import yaml

from mrta_rl.envs import AuctionParams

ROOT = Path(__file__).resolve().parents[2]
MARKDOWN = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
INLINE = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")  # [text](target)
REFERENCE = re.compile(r"^\s*\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.MULTILINE)  # [id]: target
HTML = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']""")
WEB = re.compile(r"^https?://")  # web pages do not depend on what sits next to a clone


def links(text: str) -> list[str]:
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)  # code blocks hold no links
    return [m for pattern in (INLINE, REFERENCE, HTML) for m in pattern.findall(text)]


def test_link_parser():
    text = '[a](docs/x.md) ![b](img.png "t") [c](#anchor)\n[d]: ../out.md\n<img src="p.png">'
    text += "\n```\n[e](not/a/link.md)\n```"
    assert links(text) == ["docs/x.md", "img.png", "#anchor", "../out.md", "p.png"]


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """Links of one markdown file that leave the repository or name a missing file."""
    bad = []
    for target in links(path.read_text()):
        if WEB.match(target) or target.startswith("#"):
            continue
        file_part = target.split("#", 1)[0].split("?", 1)[0]
        resolved = (path.parent / file_part).resolve()
        if "://" in target or target.startswith("/") or not resolved.is_relative_to(root):
            bad.append(f"{target} (outside the repository)")
        elif not resolved.exists():
            bad.append(f"{target} (no such file)")
    return bad


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_stay_in_the_repository(path):
    assert broken_links(path) == []
    assert "shared/spec" not in path.read_text(), "cite docs/spec/, not the outside spec"


def test_broken_links_are_found(tmp_path):
    (tmp_path / "there.md").write_text("x")
    page = tmp_path / "page.md"
    page.write_text("[a](there.md) [b](../shared/spec/auction_env.md) [c](gone.md) [d](/etc/x)")
    assert broken_links(page, root=tmp_path) == [
        "../shared/spec/auction_env.md (outside the repository)",
        "gone.md (no such file)",
        "/etc/x (outside the repository)",
    ]


def test_spec_parameter_table_matches_auction_params():
    text = (ROOT / "docs" / "spec" / "auction_env.md").read_text()
    rows = dict(re.findall(r"^\| `(\w+)` \| ([^|]+?) \|", text, flags=re.MULTILINE))
    defaults = {f.name: f.default for f in dataclasses.fields(AuctionParams)}
    assert set(rows) == set(defaults), "every AuctionParams field has one row in the spec table"
    for name, cell in rows.items():
        if defaults[name] is None:  # arrival_rate: resolved from the system
            assert cell == "m / 6" and AuctionParams().resolve(12).arrival_rate == 2.0
        else:
            value = yaml.safe_load(cell)
            expected = defaults[name]
            assert (list(expected) if isinstance(expected, tuple) else expected) == value, name
