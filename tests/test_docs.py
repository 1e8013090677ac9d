"""The documentation is self-contained: its links stay inside the repository and resolve.

The docs site builds with warnings as errors, every hand-written page is in its nav, the README
stays short, and the product (package, configs, README, user docs) carries no history: no issue
numbers and no commit hashes (the lab notebook, docs/notebook.md, keeps them). Also checks that
the parameter table of docs/spec/auction_env.md agrees with ``AuctionParams``.
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import unicodedata
from pathlib import Path

import pytest
import yaml

from mrta_rl.envs import AuctionParams

ROOT = Path(__file__).resolve().parents[1]
MARKDOWN = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
NOTEBOOK = ROOT / "docs" / "notebook.md"  # the lab notebook: history may stay there
GENERATED = ROOT / "docs" / "results"  # reports written by scripts/report.py, reached by links
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


def slug(heading: str) -> str:
    """The anchor of a heading, as Python-Markdown's toc (mkdocs) and GitHub make it."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading: its text
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def anchors(path: Path) -> set[str]:
    """The anchors of a markdown file's headings."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.DOTALL)
    return {slug(h) for h in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, flags=re.MULTILINE)}


def test_anchors_are_made_as_the_site_makes_them():
    assert slug("Task-switch setup cost (`env.switch_ticks`)") == (
        "task-switch-setup-cost-envswitch_ticks"
    )
    assert slug("What the partition costs") == "what-the-partition-costs"
    assert slug("Read [the spec](spec.md) first") == "read-the-spec-first"


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """Links of one markdown file that leave the repository, name a missing file or anchor."""
    bad = []
    for target in links(path.read_text()):
        if WEB.match(target):
            continue
        file_part, _, anchor = target.split("?", 1)[0].partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path.resolve()
        if "://" in target or target.startswith("/") or not resolved.is_relative_to(root):
            bad.append(f"{target} (outside the repository)")
        elif not resolved.exists():
            bad.append(f"{target} (no such file)")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            bad.append(f"{target} (no such heading)")
    return bad


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_stay_in_the_repository(path):
    assert broken_links(path) == []
    assert "shared/spec" not in path.read_text(), "cite docs/spec/, not the outside spec"


def test_broken_links_are_found(tmp_path):
    (tmp_path / "there.md").write_text("# Title\n\n## A section\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[a](there.md) [b](../shared/spec/auction_env.md) [c](gone.md) [d](/etc/x)\n"
        "[e](there.md#a-section) [f](there.md#gone) [g](#own) [h](#missing)\n\n## Own\n"
    )
    assert broken_links(page, root=tmp_path) == [
        "../shared/spec/auction_env.md (outside the repository)",
        "gone.md (no such file)",
        "/etc/x (outside the repository)",
        "there.md#gone (no such heading)",
        "#missing (no such heading)",
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


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines; details belong in docs/"


# History in the product: "issue 12" and commit hashes (7-40 hex digits with a letter and a
# digit, so neither plain numbers nor words count) belong in git and the lab notebook.
ISSUE = re.compile(r"\bissues?\s*#?\s*\d+", re.IGNORECASE)
HASH = re.compile(r"(?<![\w.])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}(?![\w.])")


def history_marks(text: str) -> list[str]:
    """Issue references and commit hashes in a text."""
    return [m.group(0) for pattern in (ISSUE, HASH) for m in pattern.finditer(text)]


def test_history_marks_are_found():
    text = "see issue 12, Issue #3 and issues 4; commit 557b1e9 (or 9739da3f0c)."
    assert history_marks(text) == ["issue 12", "Issue #3", "issues 4", "557b1e9", "9739da3f0c"]
    clean = "seed 1000000 + b, float64, an issue of scale, 0x9e3779b9, 2.26e23, v1.2.3, abcdef"
    assert history_marks(clean) == []


def product_files(area: str) -> list[Path]:
    if area == "README.md":
        return [ROOT / "README.md"]
    if area == "user docs":
        return [p for p in MARKDOWN if p.is_relative_to(ROOT / "docs") and p != NOTEBOOK]
    suffixes = {"mrta_rl": {".py", ".md", ".yaml"}, "conf": {".yaml", ".py"}}[area]
    return sorted(p for p in (ROOT / area).rglob("*") if p.suffix in suffixes)


@pytest.mark.parametrize(
    "area",
    ["mrta_rl", "conf", "README.md", "user docs"],
)
def test_the_product_carries_no_history(area):
    files = product_files(area)
    assert files, f"nothing to check in {area}"
    found = {
        str(p.relative_to(ROOT)): marks for p in files if (marks := history_marks(p.read_text()))
    }
    assert found == {}, "issue numbers and commit hashes belong in git and docs/notebook.md"


def nav_pages(nav) -> list[str]:
    """The markdown files that mkdocs.yml's nav lists."""
    if isinstance(nav, str):
        return [nav]
    if isinstance(nav, dict):
        return [page for value in nav.values() for page in nav_pages(value)]
    return [page for item in nav for page in nav_pages(item)]


def test_every_written_page_is_in_the_nav():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    listed = {ROOT / "docs" / page for page in nav_pages(config["nav"])}
    written = {p for p in MARKDOWN if p.is_relative_to(ROOT / "docs")}
    written -= {p for p in written if p.is_relative_to(GENERATED)}  # reached by links
    assert sorted(written - listed) == [], "add the page to mkdocs.yml's nav"
    assert sorted(listed - written) == [], "the nav lists a page that does not exist"


def mkdocs_build(config: Path, site: Path) -> subprocess.CompletedProcess[str]:
    for module in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        pytest.importorskip(module, reason="the docs extra is not installed: pip install .[docs]")
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict"]  # --quiet would hide the warnings
        + ["--config-file", str(config), "--site-dir", str(site)],
        cwd=config.parent,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    result = mkdocs_build(ROOT / "mkdocs.yml", tmp_path / "site")
    assert result.returncode == 0, result.stdout + result.stderr
    api = (tmp_path / "site" / "api" / "envs" / "index.html").read_text()
    assert "AuctionEnv" in api and "batch_size" in api, "the API pages hold the docstrings"


def test_a_broken_link_fails_the_site_build(tmp_path):
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "index.md").write_text("# Home\n\n[a](gone.md) [b](#nowhere)\n")
    site = {"site_name": "t", "strict": True, "validation": config["validation"]}
    (tmp_path / "mkdocs.yml").write_text(yaml.safe_dump(site))
    result = mkdocs_build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert result.returncode != 0
    assert "gone.md" in result.stderr and "nowhere" in result.stderr


# ------------------------------------------------------------------ the tables of learners
def marked_pages() -> list[Path]:
    from mrta_rl.learners.catalog import TABLE_START

    return [p for p in MARKDOWN if TABLE_START in p.read_text()]


def test_the_tables_of_learners_are_built_from_the_registry():
    """Every marked table is the registry's (python scripts/learner_table.py rewrites them)."""
    from mrta_rl.learners.catalog import learner_table, with_learner_table
    from mrta_rl.learners.registry import learner_files

    pages = marked_pages()
    assert {ROOT / "docs" / "index.md", ROOT / "docs" / "guide" / "train.md"} <= set(pages)
    table = learner_table()
    for name in learner_files():  # mappo, ippo, net_es, ... every yaml of conf/learner/
        assert f"\n| `{name}` |" in table, name
    stale = [
        str(p.relative_to(ROOT))
        for p in pages
        if with_learner_table(p.read_text(), table) != p.read_text()
    ]
    assert stale == [], "run python scripts/learner_table.py"


def test_a_learner_added_to_the_search_path_makes_the_tables_stale(tmp_path):
    from mrta_rl.learners.catalog import learner_table, with_learner_table

    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "toy.yaml").write_text(
        "_target_: tests.plugins.toy_learner.ToyLearner\n_partial_: true\n"
    )
    table = learner_table([tmp_path])
    assert "| `toy` | Toy bidder | tabular | numpy loop | no | Per-robot bid rate," in table
    page = (ROOT / "docs" / "guide" / "train.md").read_text()
    assert with_learner_table(page, table) != page
    with pytest.raises(ValueError, match="without its"):
        with_learner_table(table.rpartition("\n")[0], table)  # a start marker and no end


@pytest.mark.parametrize("page, kind", [("learners.md", "tabular"), ("neural.md", "neural")])
def test_each_family_page_has_a_row_for_every_learner_of_its_kind(page, kind):
    """docs/learners.md and docs/neural.md describe every learner of their kind in a table."""
    from mrta_rl.learners.registry import learner_files, learner_named

    text = (ROOT / "docs" / page).read_text()
    rows = set(re.findall(r"^\| `(\w+)` \|", text, flags=re.MULTILINE))
    of_kind = {n for n in learner_files() if learner_named(n).kind == kind}
    assert sorted(of_kind - rows) == []
