"""Check the claims of paper Section 6 against our aggregated results, one verdict per system.

Each claim is a statement of §6.1 (CTR), §6.2 (ITR) or §6.3 (learning space) turned into a test
on the means over seeds; the verdict is ``holds``, ``does not hold`` or ``not evaluable`` (a
learner it needs is missing), with the numbers. ``separation`` says whether the 95 % intervals of
the compared means are disjoint (``clear``) or overlap (``CIs overlap``: the ordering of the means
may be noise). Vague words get a stated threshold: "a bit lower" = lower by at most
:data:`A_BIT_PP` percentage points.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrta_rl.reports.aggregate import CellSummary, learner_label, system_label
from mrta_rl.reports.stats import MeanCI

TABULAR = ("cql", "semi_cql", "dql", "subg_cql")  # the four methods the paper compares
A_BIT_PP = 10.0  # "a bit lower" (§6.1): at most this many percentage points lower
HOLDS, FAILS, NOT_EVALUABLE = "holds", "does not hold", "not evaluable"

Cells = dict[str, CellSummary]  # learner -> summary, one system


@dataclass(frozen=True)
class ClaimResult:
    """Verdict of one claim on one system.

    Attributes:
        claim: Short id (``cql_best_ctr``...).
        statement: The paper's claim and where it is made.
        system: System name, or ``"all"`` for claims across systems.
        verdict: ``holds``, ``does not hold`` or ``not evaluable``.
        separation: ``clear``, ``CIs overlap`` or ``""`` (not applicable).
        evidence: The numbers the verdict rests on.
    """

    claim: str
    statement: str
    system: str
    verdict: str
    separation: str
    evidence: str


def _fmt(value: MeanCI) -> str:
    return value.format(1)


def _separated(a: MeanCI, b: MeanCI) -> bool:
    """True if the two 95 % intervals are disjoint (False when an interval is undefined)."""
    if math.isnan(a.ci95) or math.isnan(b.ci95):
        return False
    return a.high < b.low or b.high < a.low


def _separation(pairs: Sequence[tuple[MeanCI, MeanCI]]) -> str:
    return "clear" if all(_separated(a, b) for a, b in pairs) else "CIs overlap"


def _missing(cells: Cells, needed: Sequence[str]) -> list[str]:
    return [learner_label(n) for n in needed if n not in cells]


def _verdict(ok: bool) -> str:
    return HOLDS if ok else FAILS


def _extreme(
    cells: Cells, value: Callable[[CellSummary], MeanCI], target: str, lowest: bool
) -> tuple[bool, str, str]:
    """Is ``target`` the lowest/highest of the four methods? -> (ok, separation, evidence)."""
    values = {n: value(cells[n]) for n in TABULAR}
    sign = 1.0 if lowest else -1.0
    ranked = sorted(values, key=lambda n: sign * values[n].mean)
    ok = ranked[0] == target
    others = [values[n] for n in TABULAR if n != target]
    evidence = ", ".join(f"{learner_label(n)} {_fmt(values[n])}" for n in ranked)
    return ok, _separation([(values[target], o) for o in others]), evidence


def _claim_h_above_l(cells: Cells) -> tuple[str, str, str]:
    present = [n for n in TABULAR if n in cells]
    if not present:
        return NOT_EVALUABLE, "", "no tabular learner"
    pairs = [(cells[n].ctr[("all", "H")], cells[n].ctr[("all", "L")]) for n in present]
    ok = all(h.mean > low.mean for h, low in pairs)
    evidence = "; ".join(
        f"{learner_label(n)} H {_fmt(h)} vs L {_fmt(low)}"
        for n, (h, low) in zip(present, pairs, strict=True)
    )
    return _verdict(ok), _separation(pairs), evidence


def _claim_cql_best_overall(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, TABULAR):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, TABULAR))}"
    results = [
        _extreme(cells, lambda c, p=p: c.ctr[("all", p)], "cql", lowest=False) for p in ("L", "H")
    ]
    ok = all(r[0] for r in results)
    sep = "clear" if all(r[1] == "clear" for r in results) else "CIs overlap"
    return _verdict(ok), sep, f"overall CTR L: {results[0][2]} | H: {results[1][2]}"


def _claim_cql_best_each_type(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, TABULAR):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, TABULAR))}"
    cql = cells["cql"]
    keys = [(t, p) for t in cql.task_types for p in ("L", "H")]
    lost = []
    for key in keys:
        best = max(TABULAR, key=lambda n: cells[n].ctr[key].mean)
        if best != "cql" and not math.isnan(cells[best].ctr[key].mean):
            lost.append(
                f"{key[0]}{key[1]} ({learner_label(best)} {_fmt(cells[best].ctr[key])} vs "
                f"CQL {_fmt(cql.ctr[key])})"
            )
    evidence = f"CQL highest in {len(keys) - len(lost)}/{len(keys)} task type x priority cells"
    if lost:
        evidence += "; not in: " + ", ".join(lost)
    return _verdict(not lost), "", evidence


def _claim_subg_bit_lower(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, ("cql", "subg_cql")):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, ('cql', 'subg_cql')))}"
    parts, ok, pairs = [], True, []
    for p in ("L", "H"):
        cql, subg = cells["cql"].ctr[("all", p)], cells["subg_cql"].ctr[("all", p)]
        gap = cql.mean - subg.mean
        ok = ok and 0.0 < gap <= A_BIT_PP
        pairs.append((cql, subg))
        parts.append(f"{p}: CQL {_fmt(cql)} vs subG-CQL {_fmt(subg)} (gap {gap:+.1f} pp)")
    return _verdict(ok), _separation(pairs), "; ".join(parts) + f"; 'a bit' = (0, {A_BIT_PP:g}] pp"


def _claim_dql_lowest_low_ctr(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, TABULAR):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, TABULAR))}"
    ok, sep, evidence = _extreme(cells, lambda c: c.ctr[("all", "L")], "dql", lowest=True)
    return _verdict(ok), sep, f"overall CTR L, ascending: {evidence}"


def _claim_semi_vs_dql_ctr(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, ("semi_cql", "dql")):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, ('semi_cql', 'dql')))}"
    semi, dql = cells["semi_cql"].ctr, cells["dql"].ctr
    ok = semi[("all", "L")].mean > dql[("all", "L")].mean and (
        semi[("all", "H")].mean < dql[("all", "H")].mean
    )
    pairs = [(semi[("all", p)], dql[("all", p)]) for p in ("L", "H")]
    evidence = "; ".join(
        f"{p}: semi-CQL {_fmt(semi[('all', p)])} vs DQL {_fmt(dql[('all', p)])}" for p in ("L", "H")
    )
    return _verdict(ok), _separation(pairs), evidence


def _claim_itr_extreme(target: str, lowest: bool) -> Callable[[Cells], tuple[str, str, str]]:
    def check(cells: Cells) -> tuple[str, str, str]:
        if _missing(cells, TABULAR):
            return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, TABULAR))}"
        ok, sep, evidence = _extreme(cells, lambda c: c.overall_itr, target, lowest)
        robots = cells[target].robots
        sign = 1.0 if lowest else -1.0
        per_robot = sum(
            min(TABULAR, key=lambda n: sign * cells[n].itr[r].mean) == target for r in robots
        )
        word = "lowest" if lowest else "highest"
        return (
            _verdict(ok),
            sep,
            (
                f"mean ITR over robots, {'ascending' if lowest else 'descending'}: {evidence}; "
                f"{learner_label(target)} {word} for {per_robot}/{len(robots)} robots"
            ),
        )

    return check


def _claim_semi_itr_between(cells: Cells) -> tuple[str, str, str]:
    needed = ("cql", "semi_cql", "dql")
    if _missing(cells, needed):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, needed))}"
    cql, semi, dql = (cells[n].overall_itr for n in needed)
    ok = cql.mean < semi.mean < dql.mean
    return (
        _verdict(ok),
        _separation([(cql, semi), (semi, dql)]),
        (f"mean ITR: CQL {_fmt(cql)} < semi-CQL {_fmt(semi)} < DQL {_fmt(dql)} expected"),
    )


def _analytic(cell: CellSummary) -> int | None:
    values = cell.learning_space.get("analytic")
    return int(values[0]) if values else None


def _sci(value: int) -> str:
    return f"{value:.3e}" if value >= 10**6 else f"{value:,}"


def _claim_space_order(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, TABULAR):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, TABULAR))}"
    dims = {n: _analytic(cells[n]) for n in TABULAR}
    if any(v is None for v in dims.values()):
        return NOT_EVALUABLE, "", "a learner reports no analytic learning space"
    ok = dims["cql"] > dims["subg_cql"] > max(dims["semi_cql"], dims["dql"])
    evidence = ", ".join(f"{learner_label(n)} {_sci(dims[n])}" for n in TABULAR)
    return _verdict(ok), "", evidence


def _claim_space_semi_eq_dql(cells: Cells) -> tuple[str, str, str]:
    if _missing(cells, ("semi_cql", "dql")):
        return NOT_EVALUABLE, "", f"missing: {', '.join(_missing(cells, ('semi_cql', 'dql')))}"
    semi, dql = _analytic(cells["semi_cql"]), _analytic(cells["dql"])
    if semi is None or dql is None:
        return NOT_EVALUABLE, "", "a learner reports no analytic learning space"
    return _verdict(semi == dql), "", f"semi-CQL {_sci(semi)}, DQL {_sci(dql)}"


def _claim_more_robots_higher_ctr(cells: Cells) -> tuple[str, str, str]:
    present = [n for n in TABULAR if n in cells and cells[n].capable_robots]
    if not present:
        return NOT_EVALUABLE, "", "no tabular learner with a known system table"
    parts, ok = [], True
    for name in present:
        cell = cells[name]
        counts = np.array([cell.capable_robots.get(t, 0) for t in cell.task_types], dtype=float)
        ctr = np.array(
            [np.nanmean([cell.ctr[(t, p)].mean for p in ("L", "H")]) for t in cell.task_types]
        )
        keep = ~np.isnan(ctr)
        if keep.sum() < 3 or np.std(counts[keep]) == 0:
            parts.append(f"{learner_label(name)}: too few distinct types")
            continue
        r = float(np.corrcoef(counts[keep], ctr[keep])[0, 1])
        ok = ok and r > 0
        parts.append(f"{learner_label(name)} r = {r:+.2f}")
    return (
        _verdict(ok),
        "",
        (
            "Pearson r between a type's number of capable robots and its mean L/H CTR: "
            + ", ".join(parts)
        ),
    )


# (id, statement, check): checked once per system
CLAIMS: tuple[tuple[str, str, Callable[[Cells], tuple[str, str, str]]], ...] = (
    (
        "h_above_l",
        "CTR of high-priority tasks is higher than of low-priority tasks, for every method (§6.1)",
        _claim_h_above_l,
    ),
    (
        "cql_best_ctr",
        "CQL has the best CTR, for low- and high-priority tasks (§6 summary; overall "
        "CTR per priority)",
        _claim_cql_best_overall,
    ),
    (
        "cql_best_each_type",
        "CQL has the highest CTR for each type of task (§6.1)",
        _claim_cql_best_each_type,
    ),
    (
        "subg_ctr_bit_lower",
        "subG-CQL's CTR is a bit lower than CQL's, for both priorities (§6.1, §6 summary)",
        _claim_subg_bit_lower,
    ),
    (
        "dql_lowest_ctr_l",
        "DQL has the lowest CTR for low-priority tasks (§6.1)",
        _claim_dql_lowest_low_ctr,
    ),
    (
        "semi_vs_dql_ctr",
        "semi-CQL's CTR is higher than DQL's for low-priority tasks and lower for "
        "high-priority tasks (§6.1)",
        _claim_semi_vs_dql_ctr,
    ),
    (
        "subg_lowest_itr",
        "subG-CQL has the lowest ITR (§6.2, §6 summary)",
        _claim_itr_extreme("subg_cql", lowest=True),
    ),
    ("dql_highest_itr", "DQL has the highest ITR (§6.2)", _claim_itr_extreme("dql", lowest=False)),
    (
        "semi_itr_between",
        "semi-CQL's ITR is better than DQL's and worse than CQL's (§6.2)",
        _claim_semi_itr_between,
    ),
    (
        "space_order",
        "Learning space: CQL > subG-CQL > semi-CQL, DQL (§6.3, Table 9)",
        _claim_space_order,
    ),
    (
        "space_semi_eq_dql",
        "semi-CQL and DQL have the same learning space dimension (Table 9)",
        _claim_space_semi_eq_dql,
    ),
    (
        "more_robots_higher_ctr",
        "Task types more robots can do have higher CTR (§6.1)",
        _claim_more_robots_higher_ctr,
    ),
)


def check_claims(summaries: dict[tuple[str, str], CellSummary]) -> list[ClaimResult]:
    """Verdicts of every claim on every system, plus the cross-system learning space claim.

    Args:
        summaries: ``(system, learner) -> summary`` (:func:`~mrta_rl.reports.summarize_runs`).

    Returns:
        One result per claim and system, in :data:`CLAIMS` order, then the cross-system one.
    """
    systems = list(dict.fromkeys(system for system, _ in summaries))
    results = []
    for claim, statement, check in CLAIMS:
        for system in systems:
            cells = {learner: s for (sys_, learner), s in summaries.items() if sys_ == system}
            verdict, separation, evidence = check(cells)
            results.append(ClaimResult(claim, statement, system, verdict, separation, evidence))
    results.append(_claim_system2_larger(summaries))
    return results


def _claim_system2_larger(summaries: dict[tuple[str, str], CellSummary]) -> ClaimResult:
    statement = "System-II's learning space is larger than System-I's, for every method (§6.3)"
    parts, ok, seen = [], True, 0
    for name in TABULAR:
        one, two = summaries.get(("system1", name)), summaries.get(("system2", name))
        if one is None or two is None or _analytic(one) is None or _analytic(two) is None:
            continue
        seen += 1
        ok = ok and _analytic(two) > _analytic(one)
        parts.append(
            f"{learner_label(name)}: {system_label('system1')} {_sci(_analytic(one))}, "
            f"{system_label('system2')} {_sci(_analytic(two))}"
        )
    if seen == 0:
        return ClaimResult(
            "space_system2_larger",
            statement,
            "all",
            NOT_EVALUABLE,
            "",
            "needs a tabular learner on both system1 and system2",
        )
    return ClaimResult("space_system2_larger", statement, "all", _verdict(ok), "", "; ".join(parts))


@dataclass(frozen=True)
class ClaimAlong:
    """Where one claim holds along a swept parameter (``env.switch_ticks``, team size...).

    Attributes:
        claim: Claim id.
        statement: The paper's claim.
        system: System name (or ``"all"``).
        holds_at: Values of the parameter where it holds, ascending.
        fails_at: Values where it does not hold.
        not_evaluable_at: Values where a learner it compares is missing.
    """

    claim: str
    statement: str
    system: str
    holds_at: tuple[Any, ...]
    fails_at: tuple[Any, ...]
    not_evaluable_at: tuple[Any, ...]


def claims_along(
    summaries_by_value: Mapping[Any, dict[tuple[str, str], CellSummary]],
) -> list[ClaimAlong]:
    """Check every claim at every value of a swept parameter.

    Args:
        summaries_by_value: Parameter value -> the summaries of the runs made with that value.

    Returns:
        One row per claim and system, in :func:`check_claims` order, listing the values where the
        claim holds, does not hold, and cannot be evaluated.
    """
    verdicts: dict[tuple[str, str], dict[str, list[Any]]] = {}
    statements: dict[str, str] = {}
    for value in sorted(summaries_by_value):
        for result in check_claims(summaries_by_value[value]):
            statements[result.claim] = result.statement
            cell = verdicts.setdefault((result.claim, result.system), {})
            cell.setdefault(result.verdict, []).append(value)
    return [
        ClaimAlong(
            claim,
            statements[claim],
            system,
            tuple(cell.get(HOLDS, ())),
            tuple(cell.get(FAILS, ())),
            tuple(cell.get(NOT_EVALUABLE, ())),
        )
        for (claim, system), cell in verdicts.items()
    ]
