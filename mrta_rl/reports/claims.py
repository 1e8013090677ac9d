"""The claims of paper Section 6 as data, checked on the summary: one verdict per system.

``separation`` says whether the 95 % intervals of the compared means are disjoint (``clear``):
with overlapping intervals the ordering of the means may be noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from mrta_rl.reports.frame import stat, system_label
from mrta_rl.reports.stats import MeanCI
from mrta_rl.reports.tables import big_int

TABULAR = ("cql", "semi_cql", "dql", "subg_cql")  # the four methods the paper compares
A_BIT_PP = 10.0  # "a bit lower" (§6.1): at most this many percentage points lower
HOLDS, FAILS, NOT_EVALUABLE = "holds", "does not hold", "not evaluable"
CLAIMS_HEADER = ["claim", "system", "verdict", "separation", "statement", "evidence"]


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

    def get(self, name: str, metric: str, item: str = "", priority: str = "") -> MeanCI:
        """A learner's aggregate of one metric value."""
        return stat(self.by_learner[name], metric, item, priority)

    def items(self, name: str, metric: str) -> list[str]:
        """Task types (``ctr``, ``capable_robots``) or robots (``itr``) of a cell, not ``all``."""
        rows = self.by_learner[name]
        items = rows[rows["metric"] == metric]["item"]
        return [i for i in dict.fromkeys(items) if i not in ("all", "mean")]

    def analytic(self, name: str) -> int | None:
        """The exact analytic learning space of a learner (None if it reports none)."""
        rows = self.by_learner.get(name)
        if rows is None:
            return None
        rows = rows[(rows["metric"] == "learning_space") & (rows["item"] == "analytic")]
        return int(rows["first"].iloc[0]) if len(rows) else None

    def missing(self, needed: Sequence[str]) -> str:
        """``"missing: CQL, DQL"`` for the needed learners without a cell, else ``""``."""
        gone = [self.label(n) for n in needed if n not in self]
        return f"missing: {', '.join(gone)}" if gone else ""


def _separation(pairs: Sequence[tuple[MeanCI, MeanCI]]) -> str:
    """``clear`` if each pair's 95 % intervals are disjoint (an undefined one compares False)."""
    return "clear" if all(a.high < b.low or b.high < a.low for a, b in pairs) else "CIs overlap"


def _verdict(ok: bool) -> str:
    return HOLDS if ok else FAILS


def _extreme(cells: Cells, value: Callable[[str], MeanCI], target: str, lowest: bool) -> tuple:
    """Is ``target`` the lowest/highest of the four methods? -> (ok, separation, evidence)."""
    values = {n: value(n) for n in TABULAR}
    ranked = sorted(values, key=lambda n: (1.0 if lowest else -1.0) * values[n].mean)
    others = [values[n] for n in TABULAR if n != target]
    evidence = ", ".join(f"{cells.label(n)} {values[n].format(1)}" for n in ranked)
    return ranked[0] == target, _separation([(values[target], o) for o in others]), evidence


def _h_above_l(cells: Cells) -> tuple[str, str, str]:
    present = [n for n in TABULAR if n in cells]
    if not present:
        return NOT_EVALUABLE, "", "no tabular learner"
    pairs = [(cells.get(n, "ctr", "all", "H"), cells.get(n, "ctr", "all", "L")) for n in present]
    evidence = "; ".join(
        f"{cells.label(n)} H {h.format(1)} vs L {low.format(1)}"
        for n, (h, low) in zip(present, pairs, strict=True)
    )
    return _verdict(all(h.mean > low.mean for h, low in pairs)), _separation(pairs), evidence


def _cql_best_overall(cells: Cells) -> tuple[str, str, str]:
    results = [
        _extreme(cells, lambda n, p=p: cells.get(n, "ctr", "all", p), "cql", lowest=False)
        for p in ("L", "H")
    ]
    sep = "clear" if all(r[1] == "clear" for r in results) else "CIs overlap"
    evidence = f"overall CTR L: {results[0][2]} | H: {results[1][2]}"
    return _verdict(all(r[0] for r in results)), sep, evidence


def _cql_best_each_type(cells: Cells) -> tuple[str, str, str]:
    keys = [(t, p) for t in cells.items("cql", "ctr") for p in ("L", "H")]
    lost = []
    for t, p in keys:
        best = max(TABULAR, key=lambda n: cells.get(n, "ctr", t, p).mean)
        if best != "cql" and not math.isnan(cells.get(best, "ctr", t, p).mean):
            lost.append(
                f"{t}{p} ({cells.label(best)} {cells.get(best, 'ctr', t, p).format(1)} vs "
                f"CQL {cells.get('cql', 'ctr', t, p).format(1)})"
            )
    evidence = f"CQL highest in {len(keys) - len(lost)}/{len(keys)} task type x priority cells"
    return _verdict(not lost), "", evidence + ("; not in: " + ", ".join(lost) if lost else "")


def _subg_bit_lower(cells: Cells) -> tuple[str, str, str]:
    parts, ok, pairs = [], True, []
    for p in ("L", "H"):
        cql, subg = cells.get("cql", "ctr", "all", p), cells.get("subg_cql", "ctr", "all", p)
        gap = cql.mean - subg.mean
        ok = ok and 0.0 < gap <= A_BIT_PP
        pairs.append((cql, subg))
        parts.append(f"{p}: CQL {cql.format(1)} vs subG-CQL {subg.format(1)} (gap {gap:+.1f} pp)")
    return _verdict(ok), _separation(pairs), "; ".join(parts) + f"; 'a bit' = (0, {A_BIT_PP:g}] pp"


def _dql_lowest_low_ctr(cells: Cells) -> tuple[str, str, str]:
    ok, sep, evidence = _extreme(cells, lambda n: cells.get(n, "ctr", "all", "L"), "dql", True)
    return _verdict(ok), sep, f"overall CTR L, ascending: {evidence}"


def _semi_vs_dql_ctr(cells: Cells) -> tuple[str, str, str]:
    semi, dql = ({p: cells.get(n, "ctr", "all", p) for p in "LH"} for n in ("semi_cql", "dql"))
    ok = semi["L"].mean > dql["L"].mean and semi["H"].mean < dql["H"].mean
    evidence = "; ".join(
        f"{p}: semi-CQL {semi[p].format(1)} vs DQL {dql[p].format(1)}" for p in "LH"
    )
    return _verdict(ok), _separation([(semi[p], dql[p]) for p in "LH"]), evidence


def _itr_extreme(target: str, lowest: bool) -> Callable[[Cells], tuple[str, str, str]]:
    def check(cells: Cells) -> tuple[str, str, str]:
        ok, sep, evidence = _extreme(cells, lambda n: cells.get(n, "itr", "mean"), target, lowest)
        robots = cells.items(target, "itr")
        sign = 1.0 if lowest else -1.0
        per_robot = sum(
            min(TABULAR, key=lambda n: sign * cells.get(n, "itr", r).mean) == target for r in robots
        )
        order, word = ("ascending", "lowest") if lowest else ("descending", "highest")
        count = f"{cells.label(target)} {word} for {per_robot}/{len(robots)} robots"
        return _verdict(ok), sep, f"mean ITR over robots, {order}: {evidence}; {count}"

    return check


def _semi_itr_between(cells: Cells) -> tuple[str, str, str]:
    cql, semi, dql = (cells.get(n, "itr", "mean") for n in ("cql", "semi_cql", "dql"))
    return (
        _verdict(cql.mean < semi.mean < dql.mean),
        _separation([(cql, semi), (semi, dql)]),
        f"mean ITR: CQL {cql.format(1)} < semi-CQL {semi.format(1)} < DQL {dql.format(1)} expected",
    )


def _space_order(cells: Cells) -> tuple[str, str, str]:
    dims = {n: cells.analytic(n) for n in TABULAR}
    if any(v is None for v in dims.values()):
        return NOT_EVALUABLE, "", "a learner reports no analytic learning space"
    ok = dims["cql"] > dims["subg_cql"] > max(dims["semi_cql"], dims["dql"])
    return _verdict(ok), "", ", ".join(f"{cells.label(n)} {big_int(dims[n])}" for n in TABULAR)


def _space_semi_eq_dql(cells: Cells) -> tuple[str, str, str]:
    semi, dql = cells.analytic("semi_cql"), cells.analytic("dql")
    if semi is None or dql is None:
        return NOT_EVALUABLE, "", "a learner reports no analytic learning space"
    return _verdict(semi == dql), "", f"semi-CQL {big_int(semi)}, DQL {big_int(dql)}"


def _more_robots_higher_ctr(cells: Cells) -> tuple[str, str, str]:
    present = [n for n in TABULAR if n in cells and cells.items(n, "capable_robots")]
    if not present:
        return NOT_EVALUABLE, "", "no tabular learner with a known system table"
    parts, ok = [], True
    for name in present:
        types = cells.items(name, "ctr")
        counts = np.array([cells.get(name, "capable_robots", t).mean for t in types])
        ctr = np.array(
            [np.nanmean([cells.get(name, "ctr", t, p).mean for p in "LH"]) for t in types]
        )
        keep = ~np.isnan(ctr)
        if keep.sum() < 3 or np.std(counts[keep]) == 0:
            parts.append(f"{cells.label(name)}: too few distinct types")
            continue
        r = float(np.corrcoef(counts[keep], ctr[keep])[0, 1])
        ok = ok and r > 0
        parts.append(f"{cells.label(name)} r = {r:+.2f}")
    text = "Pearson r between a type's number of capable robots and its mean L/H CTR: "
    return _verdict(ok), "", text + ", ".join(parts)


SEMI_DQL, CQL_SUBG = ("semi_cql", "dql"), ("cql", "subg_cql")
# (id, statement, learners it needs (None: checks for itself), check): once per system
CLAIMS: tuple[tuple[str, str, tuple[str, ...] | None, Callable[[Cells], tuple]], ...] = (
    ("h_above_l", "CTR of high-priority tasks is higher than of low-priority tasks, for every "
     "method (§6.1)", None, _h_above_l),
    ("cql_best_ctr", "CQL has the best CTR, for low- and high-priority tasks (§6 summary; overall "
     "CTR per priority)", TABULAR, _cql_best_overall),
    ("cql_best_each_type", "CQL has the highest CTR for each type of task (§6.1)", TABULAR,
     _cql_best_each_type),
    ("subg_ctr_bit_lower", "subG-CQL's CTR is a bit lower than CQL's, for both priorities (§6.1, "
     "§6 summary)", CQL_SUBG, _subg_bit_lower),
    ("dql_lowest_ctr_l", "DQL has the lowest CTR for low-priority tasks (§6.1)", TABULAR,
     _dql_lowest_low_ctr),
    ("semi_vs_dql_ctr", "semi-CQL's CTR is higher than DQL's for low-priority tasks and lower for "
     "high-priority tasks (§6.1)", SEMI_DQL, _semi_vs_dql_ctr),
    ("subg_lowest_itr", "subG-CQL has the lowest ITR (§6.2, §6 summary)", TABULAR,
     _itr_extreme("subg_cql", lowest=True)),
    ("dql_highest_itr", "DQL has the highest ITR (§6.2)", TABULAR, _itr_extreme("dql", False)),
    ("semi_itr_between", "semi-CQL's ITR is better than DQL's and worse than CQL's (§6.2)",
     ("cql", "semi_cql", "dql"), _semi_itr_between),
    ("space_order", "Learning space: CQL > subG-CQL > semi-CQL, DQL (§6.3, Table 9)", TABULAR,
     _space_order),
    ("space_semi_eq_dql", "semi-CQL and DQL have the same learning space dimension (Table 9)",
     SEMI_DQL, _space_semi_eq_dql),
    ("more_robots_higher_ctr", "Task types more robots can do have higher CTR (§6.1)", None,
     _more_robots_higher_ctr),
)  # fmt: skip


def check_claims(summary: pd.DataFrame) -> list[ClaimResult]:
    """Verdicts of every claim on every system, plus the cross-system learning space claim."""
    by_system = {s: Cells(rows) for s, rows in summary.groupby("system", sort=False)}
    results = []
    for claim, statement, needed, check in CLAIMS:
        for system, cells in by_system.items():
            missing = cells.missing(needed or ())
            verdict = (NOT_EVALUABLE, "", missing) if missing else check(cells)
            results.append(ClaimResult(claim, statement, system, *verdict))
    return [*results, _system2_larger(by_system)]


def _system2_larger(by_system: Mapping[str, Cells]) -> ClaimResult:
    statement = "System-II's learning space is larger than System-I's, for every method (§6.3)"
    one, two = by_system.get("system1"), by_system.get("system2")
    parts, ok = [], True
    for name in TABULAR if one and two else ():
        small, large = one.analytic(name), two.analytic(name)
        if small is None or large is None:
            continue
        ok = ok and large > small
        parts.append(
            f"{one.label(name)}: {system_label('system1')} {big_int(small)}, "
            f"{system_label('system2')} {big_int(large)}"
        )
    if not parts:
        evidence = "needs a tabular learner on both system1 and system2"
        return ClaimResult("space_system2_larger", statement, "all", NOT_EVALUABLE, "", evidence)
    return ClaimResult("space_system2_larger", statement, "all", _verdict(ok), "", "; ".join(parts))


def claims_table(results: Sequence[ClaimResult]) -> pd.DataFrame:
    """The results as a table (:data:`CLAIMS_HEADER`)."""
    rows = [[r.claim, r.system, r.verdict, r.separation, r.statement, r.evidence] for r in results]
    return pd.DataFrame(rows, columns=CLAIMS_HEADER)


def claims_along(summaries: Mapping[Any, pd.DataFrame]) -> pd.DataFrame:
    """Per claim and system, the values of a swept setting where it holds, fails, cannot tell."""
    table = pd.concat(
        [claims_table(check_claims(summaries[v])).assign(value=v) for v in sorted(summaries)]
    )
    columns = {"holds_at": HOLDS, "fails_at": FAILS, "not_evaluable_at": NOT_EVALUABLE}
    return (
        table.groupby(["claim", "system"], sort=False)
        .apply(
            lambda g: pd.Series(
                {k: tuple(g[g["verdict"] == v]["value"]) for k, v in columns.items()}
            )
        )
        .reset_index()
    )
