"""semi-CQL's growing tables: growing in place, by copy or not at all gives the same tables.

semi-CQL stores a row of ``m x (K + 1)`` values per whole-system state met, so its arrays grow
during training (``SemiCQLLearner._reserve``): in place when nothing else holds them (no copy),
else by copy. The tabular fixture (``tabular_tables.py``, 250 ticks of 4 copies) stays below the
first growth; these runs cross it several times.
"""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.learners.tabular.semi_cql import SemiCQLLearner
from tests.unit.tabular_tables import train

TICKS = 700  # 4 copies: 2,756 states met, past 1,024 rows (the first growth)
# rows, visits and sum of Q after TICKS ticks: the tables of a65b176 (before growing in place)
KNOWN = [
    ({"state": "system"}, (2756, 4843, 1315.7005362696245)),
    ({"state": "system", "alpha": 1.0, "alpha_power": 1.0}, (2756, 4843, 13116.884646089657)),
]


def _tables(
    monkeypatch, hyperparameters: dict, hold_views: bool = False, room: int = 0
) -> tuple[dict[str, np.ndarray], bool]:
    """semi-CQL's tables after :data:`TICKS` fused ticks of System-II.

    Args:
        monkeypatch: pytest's.
        hyperparameters: The learner's.
        hold_views: Keep a view of the values alive at every growth (forces the copy).
        room: Rows more to make room for at each growth (8,192: grows only once, at the start).

    Returns:
        The tables, and whether the value array is still the object it was at the start.
    """
    grow = SemiCQLLearner._reserve
    first, views = [], []

    def reserve(self: SemiCQLLearner, extra: int) -> None:
        first[:] = first or [id(self.q)]  # not a reference: that would force the copy
        if hold_views:
            views.append(self.q[:1])
        grow(self, extra + room)

    monkeypatch.setattr(SemiCQLLearner, "_reserve", reserve)
    learner = train("semi_cql", hyperparameters, TICKS, fused=True)
    return learner._table_arrays(), id(learner.q) == first[0]


@pytest.mark.parametrize(("hyperparameters", "known"), KNOWN)
def test_growing_in_place_by_copy_or_not_at_all_gives_the_same_tables(
    monkeypatch, hyperparameters, known
):
    """In place (nothing holds the arrays), by copy (a view is alive), or room made up front."""
    grown, in_place = _tables(monkeypatch, hyperparameters)
    copied, kept = _tables(monkeypatch, hyperparameters, hold_views=True)
    roomy, _ = _tables(monkeypatch, hyperparameters, room=8192)
    assert in_place and not kept  # both growth paths were taken
    n_rows, visits, q_sum = known
    assert len(grown["states"]) == len(np.unique(grown["states"])) == n_rows
    assert int(grown["visits"].sum()) == visits
    assert float(grown["q"].sum()) == pytest.approx(q_sum, rel=1e-12)
    for other in (copied, roomy):
        assert sorted(other) == sorted(grown)
        for key, value in grown.items():
            np.testing.assert_array_equal(other[key], value, err_msg=key)
