"""``net_es``: a network policy on ``reserve_es``'s rule, trained by evolution strategies.

The policy is ``reserve_es``'s (``mrta_rl/learners/search/reserve_es.py``): H slots first, then
L slots, each in slot order, one robot per slot; the H slot goes to the idle robot with the highest
preference, the L slot to the idle robot with the highest score if that score is positive. Each
score is the rule's linear term plus a small network's output for the (robot, slot) pair:

* ``score_L(i, k) = theta_L . phi(i, k) + f_L(x(i, k))``,
* ``preference_H(i, k) = theta_H . phi_H(i) + f_H(x(i, k))``,

where ``f = (f_L, f_H)`` is a one-hidden-layer tanh network over the pair's inputs
:data:`INPUTS` (what the coarse features hide: battery, the slot task's duration and auction
round, how many other robots cover the robot's types now, soon and for as long as the task would
keep it, the queued tasks of its types, the H tasks of its types due again within a few ticks).
The network's output layer starts at zero, so the untrained policy plays ``reserve_es``'s start
rule (``team_reserve`` with the given ``reserve`` and ``hold_level``) exactly.

Every count is the robot's auction zone's (spec, "Auction zones"): a robot bids only for its
zone's slots, so the robots counted (idle, free soon, free within the task's duration, the idle
share, the robots left to bid) are those of its zone, and the queue counts (its types', the
team's, the due H tasks, the rule's queue levels) are divided by the number of zones, the zone's
share of the one queue, before their thresholds and caps. A team of 1,000 robots in 100 zones then
shows each robot what a team of 10 shows it; with one zone the counts are the whole team's.
Recency (the last H arrival of the robot's types) stays team-wide.

All weights (the rule's and the network's, one flat vector) are learned from the team return by
``reserve_es``'s antithetic evolution strategies on common random numbers: every member plays the
same task streams, the members' weights are batched (one matrix product per layer over the
members) and Adam takes the step.
"""

from __future__ import annotations

from collections import namedtuple
from typing import Annotated, Any, ClassVar

import numpy as np
from numba import njit

from mrta_rl.config import Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import (
    QUEUE_THRESHOLDS_ARRAY,
    RECENCY_THRESHOLDS_ARRAY,
    battery_margin,
)
from mrta_rl.envs.state_codes import queue_levels_of, recency
from mrta_rl.envs.tasks import EMPTY, task_due, task_duration, task_high, task_round, task_type
from mrta_rl.learners.base import MemoryQuery
from mrta_rl.learners.memory import ResourceEstimate
from mrta_rl.learners.search.reserve_es import (
    FEATURES,
    HIGH_COLUMNS,
    N_FEATURES,
    N_LOW,
    WEIGHT_NAMES,
    ReserveESLearner,
)
from mrta_rl.partition import Partition

# x(i, k) for idle robot i and slot k, each in [0, 1]; robots counted are those of i's zone,
# queue counts are divided by the number of zones (module docstring)
INPUTS = (
    "battery",  # battery / battery_capacity
    "battery_low",  # the longest task of Lambda_i may send the robot to charge
    "versatility",  # |Lambda_i| / n
    "queued_h",  # H tasks of Lambda_i's types queued outside the slots, / 4 (capped)
    "queued_l",  # L tasks of Lambda_i's types queued outside the slots, / 12 (capped)
    "cover_soon",  # 1 / (1 + fewest other robots idle or free within 3 ticks over Lambda_i's types)
    "cover_idle",  # 1 / (1 + fewest other idle robots over Lambda_i's types)
    "cover_task",  # 1 / (1 + fewest other robots free within the slot task's duration, same)
    "slot_high",  # the slot holds an H task
    "duration",  # (slot task's duration - 3) / 9
    "round_2",  # the slot task is in its second auction: lost if nobody takes it now
    "contenders",  # 1 / (1 + other idle robots that may bid for the slot)
    "recharges",  # the slot task would send the robot to charge
    "team_idle",  # idle robots / robots (of the zone)
    "team_queued_h",  # H tasks queued outside the slots, / 5 (capped)
    "team_queued_l",  # L tasks queued outside the slots, / 20 (capped)
    "ending",  # 12 ticks or fewer left in the episode
    "h_due_soon",  # H tasks of Lambda_i's types due again within 3 ticks, / 2 (capped)
)
N_INPUTS = len(INPUTS)
N_HEADS = 2  # f_L, f_H
SOON = 3  # ticks of "free soon" and "due soon"
ENDING = 12  # ticks before the horizon from which holding a robot back cannot pay
STATE_FILE = "net_es.npz"

# The compiled policy's arguments, as named records (numba namedtuples):
# the env's decision point (per copy), refreshed every tick by :meth:`NetESLearner.encode`
TickView = namedtuple(
    "TickView",
    "queue queue_len t busy_until battery last_high idle mask slot_high",
)
# what does not change while the learner plays one team: Lambda_i, the rule's robot order and
# its hold margins, the encodings' thresholds, and battery capacity, drain, threshold, horizon
# and the auction zones: robot i bids in zone[i], one of ``zones`` (spec, "Auction zones")
TeamFacts = namedtuple(
    "TeamFacts", "active order margin recency_thresholds queue_thresholds scalars zone zones"
)
# the members' weights: copy b plays theta[b // group]; the network has n_hidden units
MemberWeights = namedtuple("MemberWeights", "theta group n_hidden")
# the rule's weights that depend on the bids placed so far in the tick (reserve_es.DYNAMIC)
NO_OTHER_IDLE, ONE_OTHER_IDLE, SLOT_CONTESTED = (
    FEATURES.index(name) for name in ("no_other_idle", "one_other_idle", "slot_contested")
)


@njit(cache=True, nogil=True)
def _network(x, theta, n_hidden, heads):  # pragma: no cover - compiled
    """``f(x)`` of one pair into ``heads`` ``[N_HEADS]``; ``theta`` is one flat weight vector."""
    first = N_FEATURES
    bias = first + N_INPUTS * n_hidden
    last = bias + n_hidden
    out_bias = last + n_hidden * N_HEADS
    heads[0] = theta[out_bias]
    heads[1] = theta[out_bias + 1]
    for h in range(n_hidden):
        a = theta[bias + h]
        for f in range(N_INPUTS):
            a += x[f] * theta[first + f * n_hidden + h]
        a = np.tanh(a)
        heads[0] += a * theta[last + h * N_HEADS]
        heads[1] += a * theta[last + h * N_HEADS + 1]


@njit(cache=True, nogil=True)
def policy_actions(view, team, weights, out):  # pragma: no cover - compiled
    """The actions ``out`` ``[B, m]`` of the policy of the module docstring.

    Args:
        view: :data:`TickView`, the decision point of every copy.
        team: :data:`TeamFacts`; ``scalars`` holds battery capacity, drain per tick, battery
            threshold and horizon.
        weights: :data:`MemberWeights`: copy ``b`` plays ``theta[b // group]``.
        out: ``[B, m]`` int64, the actions written.
    """
    queue, queue_len, t, busy_until = view.queue, view.queue_len, view.t, view.busy_until
    battery, last_high, idle, mask = view.battery, view.last_high, view.idle, view.mask
    slot_high = view.slot_high
    active, order, margin, scalars = team.active, team.order, team.margin, team.scalars
    recency_thresholds, queue_thresholds = team.recency_thresholds, team.queue_thresholds
    theta, group, n_hidden = weights.theta, weights.group, weights.n_hidden
    capacity, drain, threshold, horizon = scalars[0], scalars[1], scalars[2], scalars[3]
    zone, zones = team.zone, team.zones
    n_copies, m, n_actions = mask.shape
    n_slots = n_actions - 1
    n = active.shape[1]
    # A robot bids only in its zone, whose share of the one queue is 1 / zones: the robots
    # counted are its zone's, the queue counts are divided by zones (thresholds times zones)
    zone_size = np.zeros(zones, np.int64)
    for i in range(m):
        zone_size[zone[i]] += 1
    zone_thresholds = queue_thresholds * zones
    versatility = np.zeros(m)
    for i in range(m):
        for z in range(n):
            versatility[i] += active[i, z]
    everything = np.ones(n, np.bool_)
    slot_duration = np.zeros(n_slots, np.int64)
    slot_round2 = np.zeros(n_slots, np.int64)
    counts = np.zeros((n, 2), np.int64)  # the whole queue, slots included; 0 = L, 1 = H
    queued = np.zeros((n, 2), np.int64)  # outside the slots
    due_soon = np.zeros(n, np.int64)
    idle_cover = np.zeros((zones, n), np.int64)
    soon_cover = np.zeros((zones, n), np.int64)
    zone_idle = np.zeros(zones, np.int64)
    idle_left = np.zeros(zones, np.int64)
    free_in = np.zeros(m, np.int64)
    free_within = np.zeros((zones, n, 1), np.int64)  # grown to the longest slot task of a tick
    phi = np.zeros((m, N_LOW))
    low = np.zeros(m)
    preference = np.zeros(m)
    free = np.zeros(m, np.bool_)
    x = np.zeros(N_INPUTS)
    heads = np.zeros(N_HEADS)
    for b in range(n_copies):
        weights = theta[b // group]
        now = t[b]
        counts[:] = 0
        queued[:] = 0
        due_soon[:] = 0
        filled = 0
        for w in range(queue_len[b]):
            key = queue[b, w]
            if key == EMPTY:
                continue
            z, high, due = task_type(key), task_high(key), task_due(key)
            counts[z, high] += 1
            if due <= now and filled < n_slots:  # spec step 3: the slots, in queue order
                slot_duration[filled] = task_duration(key)
                slot_round2[filled] = task_round(key) == 2
                filled += 1
                continue
            queued[z, high] += 1
            if high and due <= now + SOON:
                due_soon[z] += 1
        team_high, team_low = queue_levels_of(counts, everything, zone_thresholds)
        idle_cover[:] = 0
        soon_cover[:] = 0
        zone_idle[:] = 0
        team_h = team_l = 0
        for z in range(n):
            team_h += queued[z, 1]
            team_l += queued[z, 0]
        longest = 0
        for k in range(filled):
            longest = max(longest, slot_duration[k])
        if free_within.shape[2] <= longest:
            free_within = np.zeros((zones, n, longest + 1), np.int64)
        free_within[:] = 0
        for i in range(m):
            free_in[i] = max(busy_until[b, i] - now + 1, 0)  # ticks until idle; 0 = idle
            c = zone[i]
            zone_idle[c] += idle[b, i]
            for z in range(n):
                if active[i, z]:
                    idle_cover[c, z] += idle[b, i]
                    soon_cover[c, z] += free_in[i] <= SOON
                    if free_in[i] < free_within.shape[2]:
                        free_within[c, z, free_in[i]] += 1
        # free_within[c, z, d]: zone c's robots of type z free within d ticks (a running sum
        # over d), so the pair input cover_task costs O(|Lambda_i|), not O(m |Lambda_i|)
        for c in range(zones):
            for z in range(n):
                for d in range(1, free_within.shape[2]):
                    free_within[c, z, d] += free_within[c, z, d - 1]
        # reserve_es's features (its encode), the bid-dependent ones left at 0
        for i in range(m):
            level = recency(last_high[b], now, active[i], recency_thresholds)
            own_high, own_low = queue_levels_of(counts, active[i], zone_thresholds)
            sole_idle = sole_soon = False
            for z in range(n):
                if active[i, z]:
                    sole_idle |= idle_cover[zone[i], z] == 1
                    sole_soon |= soon_cover[zone[i], z] <= 1
            phi[i, :] = 0.0
            phi[i, 0] = 1.0
            phi[i, 1] = level == 0
            phi[i, 2] = level == 1
            phi[i, 3] = own_high / 2
            phi[i, 4] = own_low / 2
            phi[i, 5] = sole_idle and idle[b, i]
            phi[i, 6] = sole_soon
            phi[i, 10] = versatility[i] / n
            phi[i, 11] = team_low / 2
            phi[i, 12] = team_high / 2
            low[i] = 0.0
            for f in range(N_LOW):
                low[i] += phi[i, f] * weights[f]
            preference[i] = 0.0
            for f in range(HIGH_COLUMNS.size):
                preference[i] += phi[i, HIGH_COLUMNS[f]] * weights[N_LOW + f]
            free[i] = idle[b, i]
            out[b, i] = 0
        ending = horizon - now <= ENDING
        idle_left[:] = zone_idle
        for high in (1, 0):  # H slots first, as team_reserve
            for k in range(n_slots):
                if slot_high[b, k] != high:
                    continue
                contenders = 0
                for i in range(m):
                    contenders += free[i] and mask[b, i, k + 1]
                best, winner = -np.inf, -1
                for r in range(m):
                    i = order[r]
                    if not (free[i] and mask[b, i, k + 1]):
                        continue
                    duration = slot_duration[k]
                    c = zone[i]
                    own_h = own_l = own_due = 0
                    fewest_soon = fewest_idle = fewest_task = m
                    for z in range(n):
                        if active[i, z]:
                            own_h += queued[z, 1]
                            own_l += queued[z, 0]
                            own_due += due_soon[z]
                            fewest_soon = min(fewest_soon, soon_cover[c, z] - 1)  # others than i
                            fewest_idle = min(fewest_idle, idle_cover[c, z] - 1)
                            others = free_within[c, z, duration] - (free_in[i] <= duration)
                            fewest_task = min(fewest_task, others)
                    x[0] = battery[b, i] / capacity
                    x[1] = battery[b, i] - margin[i] < threshold
                    x[2] = versatility[i] / n
                    x[3] = min(own_h / zones, 4.0) / 4.0
                    x[4] = min(own_l / zones, 12.0) / 12.0
                    x[5] = 1.0 / (1.0 + fewest_soon)
                    x[6] = 1.0 / (1.0 + fewest_idle)
                    x[7] = 1.0 / (1.0 + fewest_task)
                    x[8] = high
                    x[9] = (duration - 3) / 9.0
                    x[10] = slot_round2[k]
                    x[11] = 1.0 / contenders  # the robot itself is one
                    x[12] = battery[b, i] - drain * duration < threshold
                    x[13] = zone_idle[c] / zone_size[c]
                    x[14] = min(team_h / zones, 5.0) / 5.0
                    x[15] = min(team_l / zones, 20.0) / 20.0
                    x[16] = ending
                    x[17] = min(own_due / zones, 2.0) / 2.0
                    _network(x, weights, n_hidden, heads)
                    if high:
                        score = preference[i] + heads[1]
                    else:
                        others = idle_left[c] - 1  # of the robot's zone
                        score = low[i] + heads[0]
                        score += weights[NO_OTHER_IDLE] * (others == 0)
                        score += weights[ONE_OTHER_IDLE] * (others == 1)
                        score += weights[SLOT_CONTESTED] * (contenders > 1)
                        if score <= 0:
                            continue
                    if score > best:  # the first of equals in the rule's order
                        best, winner = score, i
                if winner >= 0:
                    out[b, winner] = k + 1
                    free[winner] = False
                    idle_left[zone[winner]] -= 1


def network_shapes(hidden: int) -> tuple[tuple[int, ...], ...]:
    """Shapes of the network's weights, in the flat vector's order after the rule's weights."""
    return (N_INPUTS, hidden), (hidden,), (hidden, N_HEADS), (N_HEADS,)


class NetESLearner(ReserveESLearner):
    """``reserve_es``'s rule plus a network over richer pair inputs, trained by ES (module doc).

    Args:
        hidden: Hidden units of the network.
        init_scale: Standard deviation of the first layer's start weights, times
            ``1 / sqrt(len(INPUTS))``; the output layer starts at zero.
        **kwargs: ``reserve_es``'s settings (``pairs``, ``sigma``, ``lr``, ``reserve``,
            ``hold_level``: :class:`~mrta_rl.learners.search.reserve_es.ReserveESLearner`), and
            the env, generator and partition of :class:`~mrta_rl.learners.base.Learner`.

    Attributes:
        theta: The flat weights the policy plays: the rule's ``N_FEATURES``, then the network's.
    """

    label: ClassVar[str] = "net-ES"
    state_file: ClassVar[str] = STATE_FILE  # net_es.npz: the rule's weights, then the network's
    weight_names: ClassVar[tuple[str, ...]] = WEIGHT_NAMES + INPUTS

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """The weights of every training copy's member, the weights and Adam's two moments."""
        env, partition, settings, decisions, copies = query
        weights = cls.learning_space_dimension(env, partition, settings)
        size = (copies + 3) * weights * np.dtype(np.float64).itemsize
        return ResourceEstimate(cls.__name__, up_front=size, worst=size, parts={"weights": size})

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """The weights of the rule and the network (no table)."""
        hidden = cls.complete_settings(settings)["hidden"]
        return N_FEATURES + sum(int(np.prod(shape)) for shape in network_shapes(hidden))

    def __init__(
        self,
        *,
        hidden: Annotated[int, Range(1)],
        init_scale: Annotated[float, Range(0)],
        **kwargs: Any,
    ) -> None:
        self.hidden = hidden
        super().__init__(**kwargs)  # reserve_es's settings are declared there
        first = self.rng.standard_normal((N_INPUTS, hidden)) * init_scale / np.sqrt(N_INPUTS)
        bias = self.rng.standard_normal(hidden) * init_scale
        start = [first, bias, np.zeros((hidden, N_HEADS)), np.zeros(N_HEADS)]
        self.theta = np.concatenate([self.theta, *(w.ravel() for w in start)])
        self._adam_m = np.zeros_like(self.theta)
        self._adam_v = np.zeros_like(self.theta)
        self._draw()

    def _team(self, env: AuctionEnv) -> dict[str, np.ndarray]:
        """``reserve_es``'s team facts plus ``active``, ``margin`` and ``scalars`` of TeamFacts."""
        if self._team_env is not env:
            facts = super()._team(env)
            p = env.params
            facts["active"] = env.active_tasks
            facts["margin"] = battery_margin(env)
            facts["scalars"] = np.array(
                [p.battery_capacity, p.drain_per_tick, p.battery_threshold, p.horizon], np.float64
            )
            facts["zone"] = env.robot_zone
            facts["zones"] = p.zones
        return self._team_facts

    # ------------------------------------------------------------------ policy
    def encode(self, env: AuctionEnv) -> dict[str, np.ndarray]:
        """The env arrays the policy reads, copied (the env changes them when it steps).

        ``team`` holds what the policy reads of the env's team (:meth:`_team`), so the learner
        plays whichever team the env has.
        """
        return {
            "team": self._team(env),
            "queue": env._queue.copy(),
            "queue_len": env._queue_len.copy(),
            "t": env.t.copy(),
            "busy_until": env.busy_until.copy(),
            "battery": env.battery.copy(),
            "last_high": env.last_high_arrival.copy(),
            "idle": env.idle.copy(),
            "slot_high": env.slot_high.copy(),
        }

    def _bids(
        self, view: dict[str, np.ndarray], mask: np.ndarray, theta: np.ndarray, group: int
    ) -> np.ndarray:
        """The policy's bids when copy ``b`` plays the weights ``theta[b // group]``."""
        actions = np.zeros(mask.shape[:2], np.int64)
        tick = TickView(
            view["queue"],
            view["queue_len"],
            view["t"],
            view["busy_until"],
            view["battery"],
            view["last_high"],
            view["idle"],
            np.ascontiguousarray(mask, bool),
            view["slot_high"],
        )
        facts = view["team"]
        team = TeamFacts(
            facts["active"],
            facts["order"],
            facts["margin"],
            RECENCY_THRESHOLDS_ARRAY,
            QUEUE_THRESHOLDS_ARRAY,
            facts["scalars"],
            facts["zone"],
            int(facts["zones"]),
        )
        members = MemberWeights(np.ascontiguousarray(theta, np.float64), group, self.hidden)
        policy_actions(tick, team, members, actions)
        return actions

    # ------------------------------------------------------------------ learning
    def learning_space(self) -> dict[str, int]:
        """The weights learned (no table)."""
        return {"analytic": self.theta.size, "visited": self.theta.size}
