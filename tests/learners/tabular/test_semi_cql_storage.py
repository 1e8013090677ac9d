"""semi-CQL's growing tables: growing in place or by copy gives the same tables.

semi-CQL stores a row of ``m x (K + 1)`` values per whole-system state met, so its value arrays
(``learner.q``, ``learner.visits``) grow during training: in place when nothing else holds them
(``learner.q`` stays the same array), else by copy. The tabular fixture (``tabular_tables.py``,
250 ticks of 4 copies) stays below the first growth; these runs cross it several times.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.learners.tabular.tabular_tables import (
    FIXTURE_SETTINGS,
    build,
    play_fused,
    saved_tables,
)

TICKS = 700  # 4 copies: 2,756 states met, past 1,024 rows (the first growth)
# rows, visits and sum of Q after TICKS ticks of these seeds: a change of the update rule, a
# tie-break or a draw changes them
KNOWN = [
    ({**FIXTURE_SETTINGS, "state": "system"}, (2756, 4843, 1315.7005362696245)),
    (
        {**FIXTURE_SETTINGS, "state": "system", "alpha": 1.0, "alpha_power": 1.0},
        (2756, 4843, 13116.884646089657),
    ),
]


def grown_tables(hyperparameters: dict, hold_views: bool) -> tuple[dict[str, np.ndarray], bool]:
    """semi-CQL's tables after :data:`TICKS` fused ticks of System-II.

    Args:
        hyperparameters: The learner's.
        hold_views: Keep a view of the values alive after every tick (a growth must copy).

    Returns:
        The tables as saved, and whether ``learner.q`` is still the array it was at the start.
    """
    env, learner = build("semi_cql", hyperparameters)
    first, start_size, views = id(learner.q), len(learner.q), []

    def hold(learner) -> None:
        if hold_views:
            views.append(learner.q[:1])

    play_fused(env, learner, TICKS, after_tick=hold)
    assert len(learner.q) > start_size  # the arrays grew
    return saved_tables(learner), id(learner.q) == first


@pytest.mark.parametrize(("hyperparameters", "known"), KNOWN)
def test_growing_in_place_or_by_copy_gives_the_same_tables(hyperparameters, known):
    """In place (nothing holds the arrays) or by copy (a view of them is alive)."""
    grown, in_place = grown_tables(hyperparameters, hold_views=False)
    copied, kept = grown_tables(hyperparameters, hold_views=True)
    assert in_place and not kept  # both growth paths were taken
    n_rows, visits, q_sum = known
    assert len(grown["states"]) == len(np.unique(grown["states"])) == n_rows
    assert int(grown["visits"].sum()) == visits
    assert float(grown["q"].sum()) == pytest.approx(q_sum, rel=1e-12)
    assert sorted(copied) == sorted(grown)
    for key, value in grown.items():
        np.testing.assert_array_equal(copied[key], value, err_msg=key)
