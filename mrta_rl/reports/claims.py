"""The claims of a study, checked on the summary: one verdict per system.

A claim is data, an item of ``report.claims`` (``conf/experiment/paper.yaml`` holds the paper's
Section 6): its statement, one of the checks of :data:`CHECKS`, the learners it compares and the
values it compares them on, each named ``metric/item/priority`` of the summary (``ctr/all/H``,
``itr/mean``, ``learning_space/analytic``). ``separation`` says whether the 95 % intervals of
the compared means are disjoint (``clear``): with overlapping intervals the ordering of the
means may be noise.
"""

from __future__ import annotations

import itertools
import math
import operator
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Protocol

import numpy as np
import pandas as pd

from mrta_rl.config import Choices, ConfigError, check_fields
from mrta_rl.reports.frame import stat, system_label
from mrta_rl.reports.stats import MeanCI
from mrta_rl.reports.tables import big_int
from mrta_rl.types import PRIORITIES


class Study(Protocol):
    """What the claims read of a study (``reports/study.py``): its claims, groups and order."""

    claims: Sequence[Claim]
    groups: Mapping[str, Sequence[str]]

    def rank(self, learner: str) -> Any:
        """The learner's place in the study's row order."""


HOLDS, FAILS, NOT_EVALUABLE = "holds", "does not hold", "not evaluable"
CLAIMS_HEADER = ["claim", "system", "verdict", "separation", "statement", "evidence"]
RELATIONS = {">": operator.gt, "<": operator.lt, "=": operator.eq}  # of an order's chain
Value = MeanCI | int | None  # a summary value; a learning space is exact, None if unreported
Verdict = tuple[str, str, str]  # verdict, separation, evidence


@dataclass(frozen=True)
class ClaimResult:
    """Verdict of one claim on one system (``system`` is ``"all"`` for claims across systems)."""

    claim: str
    statement: str
    system: str
    verdict: str
    separation: str
    evidence: str


class Cells:
    """The summary of one system, read by learner name (the yaml stem of a plain configuration)."""

    def __init__(self, summary: pd.DataFrame) -> None:
        """Keep the cells of the summary (of one system) by learner."""
        self.by_learner = {n: rows for n, rows in summary.groupby("learner", sort=False)}
        self.labels = dict(zip(summary["learner"], summary["label"], strict=True))

    def __contains__(self, name: str) -> bool:
        return name in self.by_learner

    def label(self, name: str) -> str:
        """The learner's label in this report (its name if it has no run here)."""
        return self.labels.get(name, name)

    def value(self, name: str, path: str) -> Value:
        """A learner's value ``metric/item/priority``; a learning space exact (its first seed's).

        A learning space is None where the learner reports none (or has no cell here).
        """
        metric, item, priority = (*path.split("/"), "", "")[:3]
        if metric != "learning_space":
            return stat(self.by_learner[name], metric, item, priority)
        rows = self.by_learner.get(name)
        rows = rows[(rows["metric"] == metric) & (rows["item"] == item)] if rows is not None else []
        return int(rows["first"].iloc[0]) if len(rows) else None

    def items(self, name: str, metric: str) -> list[str]:
        """Task types (``ctr``, ``capable_robots``) or robots (``itr``) of a cell, not ``all``."""
        rows = self.by_learner[name]
        items = rows[rows["metric"] == metric]["item"]
        return [i for i in dict.fromkeys(items) if i not in ("all", "mean")]

    def missing(self, needed: Sequence[str]) -> str:
        """``"missing: CQL, DQL"`` for the needed learners without a cell, else ``""``."""
        gone = [self.label(n) for n in needed if n not in self]
        return f"missing: {', '.join(gone)}" if gone else ""

    def text(self, name: str, value: Value) -> str:
        """``"CQL 71.5 ± 6.4"``: the learner's label and the value."""
        return f"{self.label(name)} {_text(value)}"


def _separation(pairs: Sequence[tuple[MeanCI, MeanCI]]) -> str:
    """``clear`` if each pair's 95 % intervals are disjoint (an undefined one compares False)."""
    return "clear" if all(a.high < b.low or b.high < a.low for a, b in pairs) else "CIs overlap"


def _verdict(ok: bool) -> str:
    return HOLDS if ok else FAILS


def _text(value: Value) -> str:
    """``71.5 ± 6.4``; an exact value as :func:`big_int` writes it."""
    return big_int(value) if isinstance(value, int) else value.format(1)


def _mean(value: Value) -> float:
    return value if isinstance(value, int) else value.mean


def _chain(order: str) -> tuple[list[list[str]], list[str]]:
    """``"a > b > c, d"`` as its learner sets ``[[a], [b], [c, d]]`` and relations ``[>, >]``."""
    parts = re.split(r"\s*([<>=])\s*", order.strip())
    return [[n.strip() for n in p.split(",")] for p in parts[::2]], parts[1::2]


def _above(claim: Claim, cells: Cells, group: Sequence[str]) -> Verdict:
    """Every learner of the group that ran: its first value above its second."""
    present = [n for n in group if n in cells]
    if not present:
        return NOT_EVALUABLE, "", f"no {claim.group} learner"
    (a_name, a), (b_name, b) = claim.values.items()
    pairs = [(cells.value(n, a), cells.value(n, b)) for n in present]
    evidence = "; ".join(
        f"{cells.label(n)} {a_name} {x.format(1)} vs {b_name} {y.format(1)}"
        for n, (x, y) in zip(present, pairs, strict=True)
    )
    return _verdict(all(x.mean > y.mean for x, y in pairs)), _separation(pairs), evidence


def _best(claim: Claim, cells: Cells, group: Sequence[str]) -> Verdict:
    """The learner ranks first of the group on each value (highest, or lowest)."""
    sign, results = 1.0 if claim.lowest else -1.0, []
    for name, path in claim.values.items():
        values = {n: cells.value(n, path) for n in group}
        ranked = sorted(values, key=lambda n: sign * values[n].mean)
        others = [(values[claim.learner], values[n]) for n in group if n != claim.learner]
        evidence = ", ".join(f"{cells.label(n)} {values[n].format(1)}" for n in ranked)
        results.append((ranked[0] == claim.learner, _separation(others), f"{name}: {evidence}"))
    evidence = " | ".join(r[2] for r in results)
    if claim.count:  # the items (robots) of the value's metric where the learner ranks first
        metric = path.partition("/")[0]
        items = cells.items(claim.learner, metric)
        first = sum(
            min(group, key=lambda n: sign * cells.value(n, f"{metric}/{i}").mean) == claim.learner
            for i in items
        )
        word = "lowest" if claim.lowest else "highest"
        evidence += f"; {cells.label(claim.learner)} {word} for {first}/{len(items)} {claim.count}"
    separation = "clear" if all(r[1] == "clear" for r in results) else "CIs overlap"
    return _verdict(all(r[0] for r in results)), separation, evidence


def _best_each(claim: Claim, cells: Cells, group: Sequence[str]) -> Verdict:
    """The learner is the highest of the group in every item x priority cell of the metric."""
    ((name, path),) = claim.values.items()
    metric, learner = path.partition("/")[0], claim.learner
    keys = [(t, p) for t in cells.items(learner, metric) for p in PRIORITIES]
    lost = []
    for t, p in keys:
        best = max(group, key=lambda n: cells.value(n, f"{metric}/{t}/{p}").mean)
        if best != learner and not math.isnan(cells.value(best, f"{metric}/{t}/{p}").mean):
            ours, theirs = (cells.value(n, f"{metric}/{t}/{p}") for n in (learner, best))
            lost.append(f"{t}{p} ({cells.text(best, theirs)} vs {cells.text(learner, ours)})")
    evidence = f"{cells.label(learner)} highest in {len(keys) - len(lost)}/{len(keys)} {name} cells"
    return _verdict(not lost), "", evidence + ("; not in: " + ", ".join(lost) if lost else "")


def _gap(claim: Claim, cells: Cells, group: Sequence[str]) -> Verdict:
    """The first learner's value minus the second's, in percentage points, within (low, high]."""
    (a, b), (low, high) = claim.learners, claim.within
    parts, ok, pairs = [], True, []
    for name, path in claim.values.items():
        x, y = cells.value(a, path), cells.value(b, path)
        gap = x.mean - y.mean
        ok = ok and low < gap <= high
        pairs.append((x, y))
        parts.append(f"{name}: {cells.text(a, x)} vs {cells.text(b, y)} (gap {gap:+.1f} pp)")
    return _verdict(ok), _separation(pairs), "; ".join(parts) + f"; within ({low:g}, {high:g}] pp"


def _order(claim: Claim, cells: Cells, group: Sequence[str]) -> Verdict:
    """On each value, the learners in the order of its chain (``a > b > c, d``: c and d both)."""
    parts, ok, pairs = [], True, []
    for (name, path), chain in zip(claim.values.items(), claim.order, strict=True):
        sets, relations = _chain(chain)
        values = {n: cells.value(n, path) for n in itertools.chain(*sets)}
        if any(v is None for v in values.values()):
            return NOT_EVALUABLE, "", f"a learner reports no {path.split('/')[1]} learning space"
        for left, relation, right in zip(sets, relations, sets[1:], strict=False):
            for x, y in itertools.product(left, right):
                ok = ok and RELATIONS[relation](_mean(values[x]), _mean(values[y]))
                pairs.append((values[x], values[y]))
        texts = [", ".join(cells.text(n, values[n]) for n in s) for s in sets]
        parts.append(f"{name}: {texts[0]}" + "".join(map(" {} {}".format, relations, texts[1:])))
    exact = all(isinstance(x, int) for pair in pairs for x in pair)
    return _verdict(ok), "" if exact else _separation(pairs), "; ".join(parts)


def _capable_robots(claim: Claim, cells: Cells, group: Sequence[str]) -> Verdict:
    """Per learner, Pearson r between a type's number of capable robots and its mean L/H CTR."""
    present = [n for n in group if n in cells and cells.items(n, "capable_robots")]
    if not present:
        return NOT_EVALUABLE, "", f"no {claim.group} learner with a known system table"
    parts, ok = [], True
    for name in present:
        types = cells.items(name, "ctr")
        counts = np.array([cells.value(name, f"capable_robots/{t}").mean for t in types])
        per_type = ([cells.value(name, f"ctr/{t}/{p}").mean for p in PRIORITIES] for t in types)
        ctr = np.array([np.nanmean(values) for values in per_type])
        keep = ~np.isnan(ctr)
        if keep.sum() < 3 or np.std(counts[keep]) == 0:
            parts.append(f"{cells.label(name)}: too few distinct types")
            continue
        r = float(np.corrcoef(counts[keep], ctr[keep])[0, 1])
        ok = ok and r > 0
        parts.append(f"{cells.label(name)} r = {r:+.2f}")
    text = "Pearson r between a type's number of capable robots and its mean L/H CTR: "
    return _verdict(ok), "", text + ", ".join(parts)


def _larger_on(claim: Claim, by_system: Mapping[str, Cells], group: Sequence[str]) -> Verdict:
    """Across systems: every learner of the group has a larger value on the second system."""
    (small, large), ((_, path),) = claim.systems, claim.values.items()
    one, two = by_system.get(small), by_system.get(large)
    parts, ok = [], True
    for name in group if one and two else ():
        x, y = one.value(name, path), two.value(name, path)
        if x is None or y is None:
            continue
        ok = ok and _mean(y) > _mean(x)
        sizes = f"{system_label(small)} {_text(x)}, {system_label(large)} {_text(y)}"
        parts.append(f"{one.label(name)}: {sizes}")
    if not parts:
        return NOT_EVALUABLE, "", f"needs a {claim.group} learner on both {small} and {large}"
    return _verdict(ok), "", "; ".join(parts)


# each check: (claim, cells of one system, the learners of its group) -> verdict, and the keys
# of the claim it reads; larger_on is checked once across systems (cells by system)
CHECKS = {
    "above": (_above, ("group", "values")),
    "best": (_best, ("learner", "group", "values")),
    "best_each": (_best_each, ("learner", "group", "values")),
    "gap": (_gap, ("learners", "values", "within")),
    "order": (_order, ("values", "order")),
    "capable_robots": (_capable_robots, ("group",)),
    "larger_on": (_larger_on, ("group", "systems", "values")),
}


@dataclass(frozen=True)
class Claim:
    """One claim (an item of ``report.claims``): what it says, and what its check reads."""

    id: str  # its name in claims.csv
    statement: str  # as the report prints it
    check: Annotated[str, Choices(*CHECKS)]  # how it is checked
    group: str = ""  # the learners compared: a group of report.groups
    learner: str = ""  # the learner the claim is about (best, best_each)
    learners: tuple[str, ...] = ()  # gap: the first learner's value minus the second's
    values: dict[str, str] = field(default_factory=dict)  # name in the evidence -> value
    order: tuple[str, ...] = ()  # order: a chain per value (``a > b > c, d``)
    lowest: bool = False  # best: the lowest ranks first, not the highest
    count: str = ""  # best: also count the items where the learner ranks first (robots)
    within: tuple[float, float] = (0.0, 0.0)  # gap: (low, high] in percentage points
    systems: tuple[str, str] = ("", "")  # larger_on: the system with the smaller value first


def check_claim(raw: Any, where: str) -> Claim:
    """An item of ``report.claims`` as a :class:`Claim`, the keys its check reads present.

    Raises:
        ConfigError: naming the key (``<file>: report.claims[2].order``).
    """
    values = check_fields(Claim, raw, where, require=True)
    named = values.get("values", {})
    if not isinstance(named, Mapping) or not all(isinstance(v, str) for v in named.values()):
        raise ConfigError(f"{where}.values: must map names to metric/item/priority, got {named!r}")
    claim = Claim(**values | {"values": {str(k): v for k, v in named.items()}})
    missing = [k for k in CHECKS[claim.check][1] if not getattr(claim, k)]
    if missing:
        raise ConfigError(f"{where}: check {claim.check} needs {', '.join(missing)}")
    if claim.check == "order" and (
        len(claim.order) != len(claim.values) or any(len(_chain(c)[0]) < 2 for c in claim.order)
    ):
        raise ConfigError(f"{where}.order: one chain (a > b) per value, got {list(claim.order)}")
    return claim


def _needed(claim: Claim, study: Study, group: Sequence[str]) -> list[str]:
    """The learners a claim cannot be checked without, in the study's order."""
    if claim.check in ("best", "best_each"):
        return list(group)
    named = [n for chain in claim.order for s in _chain(chain)[0] for n in s]
    return sorted(dict.fromkeys([*named, *claim.learners]), key=study.rank)


def check_claims(summary: pd.DataFrame, study: Study) -> list[ClaimResult]:
    """Verdicts of every claim of the study on every system, then those across systems."""
    by_system = {s: Cells(rows) for s, rows in summary.groupby("system", sort=False)}
    results, across = [], []
    for claim in study.claims:
        group = study.groups.get(claim.group, ())
        if claim.check == "larger_on":
            verdict = _larger_on(claim, by_system, group)
            across.append(ClaimResult(claim.id, claim.statement, "all", *verdict))
            continue
        needed, check = _needed(claim, study, group), CHECKS[claim.check][0]
        for system, cells in by_system.items():
            missing = cells.missing(needed)
            verdict = (NOT_EVALUABLE, "", missing) if missing else check(claim, cells, group)
            results.append(ClaimResult(claim.id, claim.statement, system, *verdict))
    return [*results, *across]


def claims_table(results: Sequence[ClaimResult]) -> pd.DataFrame:
    """The results as a table (:data:`CLAIMS_HEADER`)."""
    rows = [[r.claim, r.system, r.verdict, r.separation, r.statement, r.evidence] for r in results]
    return pd.DataFrame(rows, columns=CLAIMS_HEADER)
