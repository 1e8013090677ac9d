"""A study's report policy as data (``report:`` of ``conf/experiment/*.yaml``), and its prose.

Which learners a report compares and in which order, the named groups its claims compare, the
claims, the yardstick rules, the best learner and the swept settings drawn as x axes are no
code: each experiment declares its part in a ``report:`` block of its yaml, which training
ignores and a run records in ``.hydra/config.yaml``. A report applies the blocks its runs
recorded (a study of one's own), then every shipped experiment's block, so that runs of any
experiment, or of none, are reported as the shipped studies say. The report's prose is
``conf/report/report.md``, whose blocks :class:`Prose` fills with :class:`string.Template`.
"""

from __future__ import annotations

import functools
import json
import re
import string
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mrta_rl.checked_files import read_text, read_yaml
from mrta_rl.conf_paths import conf_dir
from mrta_rl.config import ConfigError, check_fields, check_value, short_list
from mrta_rl.reports.claims import Claim, check_claim
from mrta_rl.reports.collect import CONFIG_FILE, POLICY_KEY

if TYPE_CHECKING:
    from mrta_rl.reports.collect import RunRecord

TEMPLATE = Path("report") / "report.md"  # the prose, in the conf dir
BLOCK = re.compile(r"^<!-- (\w+) -->\n", re.MULTILINE)  # a block of the template starts so


@dataclass(frozen=True)
class Axis:
    """A swept setting drawn as the x axis of a section of its own (``report.along.<key>``)."""

    label: str  # what the setting is, in the section's title and on the axis
    stem: str  # the file stem of its figures
    log_x: bool = False  # a log-scale x axis
    costs: bool = False  # also the learning space, wall time and memory against it


@dataclass(frozen=True)
class Study:
    """What a report makes of its runs: the merged ``report:`` blocks (every key optional)."""

    learners: tuple[str, ...] = ()  # row order; other learners follow alphabetically
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)  # named learner lists
    claims: tuple[Claim, ...] = ()  # the claims its report checks (reports/claims.py)
    rules: tuple[str, ...] = ()  # yardstick rules ("Learning against the rules")
    best_setting: tuple[str, ...] = ()  # rules whose best setting among the runs stands for them
    best_learner: str | None = None  # its trained runs are a yardstick of every policy
    along: dict[str, Axis] = field(default_factory=dict)  # swept settings drawn as x axes

    def rank(self, name: str) -> int:
        """A learner's row: its place in :attr:`learners`, after them if unlisted."""
        return self.learners.index(name) if name in self.learners else len(self.learners)


def check_block(block: Any, source: str) -> Study:
    """A ``report:`` block (plain data, from the file ``source``) as a checked :class:`Study`.

    Raises:
        ConfigError: naming the file and the key.
    """
    where = f"{source}: {POLICY_KEY}"
    values = check_fields(Study, block, where)
    groups = values.get("groups", {})
    if not isinstance(groups, Mapping):
        raise ConfigError(f"{where}.groups: must be a mapping of names to lists of learners")
    values["groups"] = {
        str(k): check_value(f"{where}.groups.{k}", v, tuple[str, ...]) for k, v in groups.items()
    }
    along = values.get("along", {})
    if not isinstance(along, Mapping):
        raise ConfigError(f"{where}.along: must be a mapping of settings to their axes")
    values["along"] = {
        str(k): Axis(**check_fields(Axis, v, f"{where}.along.{k}", require=True))
        for k, v in along.items()
    }
    claims = values.get("claims", ())
    values["claims"] = tuple(check_claim(c, f"{where}.claims[{i}]") for i, c in enumerate(claims))
    return Study(**values)


def merge(studies: Iterable[Study]) -> Study:
    """One study of several: their lists and mappings joined, their first scalar; the first wins."""
    merged: dict[str, Any] = {}
    for study in studies:
        for f in fields(Study):
            value, mine = getattr(study, f.name), merged.get(f.name)
            if isinstance(value, tuple):  # each item once, a claim by its id
                known = {getattr(x, "id", x) for x in mine or ()}
                new = (x for x in value if getattr(x, "id", x) not in known)
                merged[f.name] = (*(mine or ()), *new)
            elif isinstance(value, dict):
                merged[f.name] = (mine or {}) | {
                    k: v for k, v in value.items() if k not in (mine or {})
                }
            elif mine is None:
                merged[f.name] = value
    return Study(**merged)


@functools.cache
def shipped_studies() -> tuple[Study, ...]:
    """The ``report:`` block of every shipped experiment, in the order of their names."""
    paths = sorted((conf_dir() / "experiment").glob("*.yaml"))
    blocks = {path: (read_yaml(path) or {}).get(POLICY_KEY) for path in paths}
    return tuple(check_block(b, str(path)) for path, b in blocks.items() if b is not None)


def study_of(runs: Iterable[RunRecord]) -> Study:
    """The study of a report: the blocks its runs recorded, then the shipped experiments' blocks.

    A recorded block that is a shipped one counts once, in its shipped place.

    Raises:
        ConfigError: naming the file and key of a block that is not a study, or a claim whose
            group no block declares.
    """
    recorded = {}  # each distinct block once, with the first run that recorded it
    for run in runs:
        if (block := run.config.get(POLICY_KEY)) is not None:
            recorded.setdefault(json.dumps(block, sort_keys=True), (block, run.run_dir))
    own = [check_block(block, str(Path(d) / CONFIG_FILE)) for block, d in recorded.values()]
    shipped = shipped_studies()
    study = merge([*(s for s in own if s not in shipped), *shipped])
    for claim in study.claims:
        if claim.group and claim.group not in study.groups:
            known = short_list(study.groups)
            raise ConfigError(f"report.claims: {claim.id}: no group {claim.group} ({known})")
    return study


def paragraphs(*blocks: str) -> list[str]:
    """Markdown lines: each non-empty block (a heading, text, a table) and a blank line."""
    return [line for block in blocks if block for line in (block, "")]


class Prose:
    """The blocks of the report's template (``<!-- name -->`` starts one), filled by name."""

    def __init__(self, text: str) -> None:
        """Split the template into its blocks."""
        parts = BLOCK.split(text)[1:]  # name, body, name, body...
        self.blocks = {n: b.strip("\n") for n, b in zip(parts[::2], parts[1::2], strict=True)}

    @classmethod
    @functools.cache
    def shipped(cls) -> Prose:
        """The shipped template (``conf/report/report.md``)."""
        return cls(read_text(conf_dir() / TEMPLATE, 2**20, "the report's template"))

    def text(self, name: str, **values: Any) -> str:
        """One block, its ``$placeholders`` filled."""
        return string.Template(self.blocks[name]).substitute(values)

    def image(self, path: Path | None, alt: str) -> str:
        """A markdown image of a figure, or a note that there was nothing to draw."""
        return f"![{alt}]({path.name})" if path else self.text("no_figure", what=alt.lower())

    def section(self, name: str, **values: Any) -> list[str]:
        """One block as markdown lines: its paragraphs, those left empty when filled dropped."""
        return paragraphs(*(p.strip("\n") for p in self.text(name, **values).split("\n\n")))
