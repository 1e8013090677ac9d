"""A plain, one-copy Python reading of the auction spec, written from the spec, not from auction.py.

It is the oracle for the batched dynamics: tasks are dicts in a list, every rule is a few lines in
the spec's order. It shares only the random draws with ``AuctionEnv`` (the same counter-based
hashes of seed, episode, tick and draw index), so both must agree tick by tick, exactly.
"""

from __future__ import annotations

import numpy as np

from mrta_rl.envs import counter_rng as rng
from mrta_rl.envs.params import AuctionParams
from mrta_rl.systems import RobotSystem


class ReferenceAuction:
    """One copy of the auction, seeded as copy ``b`` of ``AuctionEnv(seed=s)`` is: ``s + b``."""

    def __init__(self, system: RobotSystem, params: AuctionParams, copy_seed: int, active=None):
        self.system, self.p = system, params.resolve(system.n_robots)
        self.m, self.n = system.n_robots, system.n_task_types
        self.d = system.willingness
        self.active = (self.d > 0) if active is None else np.asarray(active, bool)
        self.seed_key = rng.seed_keys(np.array([copy_seed]))
        self.episode = 0
        self.cdf = rng.poisson_cdf(self.p.arrival_rate)
        self.reset()

    def reset(self):
        """Start the copy's next episode (spec steps 1-3 of its first tick)."""
        self.episode_key = rng.episode_keys(self.seed_key, np.array([self.episode]))
        self.episode += 1
        self.t, self.next_id, self.queue = 0, 0, []
        self.busy_until = [-1] * self.m
        self.battery = [float(self.p.battery_capacity)] * self.m
        self.last_type = [None] * self.m  # type of each robot's previous task (switch cost)
        self.assigned = np.zeros((self.n, 2), int)
        self.dropped = np.zeros((self.n, 2), int)
        self.busy_ticks = np.zeros(self.m, int)
        self.pending_drops = []
        self.start_tick()

    def draws(self):
        """The tick's random draws, in the same derivation as AuctionEnv."""
        tick_key = rng.tick_keys(self.episode_key, np.array([self.t]))
        count = int(np.searchsorted(self.cdf, rng.unit_float(tick_key), side="right")[0])
        h_prio, h_kind = rng.task_hashes(tick_key, count)
        tasks = []
        for k in range(count):
            high = int(rng.unit_float(h_prio[0, k]) < self.p.p_high)
            ttype = int(rng.bounded_int(rng.high_bits(h_kind[0, k]), self.n))
            lo, hi = self.duration_range(ttype, high)
            tasks.append((high, ttype, lo + int(rng.bounded_int(h_kind[0, k], hi - lo + 1))))
        return tasks

    def duration_range(self, ttype, high):
        """Shortest and longest duration of a task of this type and priority."""
        key = "duration_high" if high else "duration_low"
        override = self.system.durations.get(self.system.task_types[ttype], {}).get(key)
        return (override.lo, override.hi) if override else getattr(self.p, key)

    def start_tick(self):
        """Spec steps 1-3."""
        self.pending_drops = []
        for high, ttype, duration in self.draws():  # step 1
            self.queue.append(
                dict(id=self.next_id, type=ttype, high=high, duration=duration, round=1, due=self.t)
            )
            self.next_id += 1
        self.queue.sort(key=lambda x: (-x["high"], x["due"], x["id"]))  # step 2
        while len(self.queue) > self.p.queue_capacity:
            self.pending_drops.append(self.queue.pop())
        self.slots = [x for x in self.queue if x["due"] <= self.t][: self.p.slots]  # step 3

    def valid_actions(self, i):
        """Robot ``i``'s valid actions: wait, and a bid for each slot of an active type if idle."""
        if not self.t > self.busy_until[i]:
            return [0]
        zone, zones = i * self.p.zones // self.m, self.p.zones  # spec, "Auction zones"
        return [0] + [
            k + 1
            for k, x in enumerate(self.slots)
            if self.active[i, x["type"]] and k % zones == zone
        ]

    def step(self, actions):
        """Spec steps 4-8; returns (team reward, individual rewards)."""
        p = self.p
        idle = [self.t > self.busy_until[i] for i in range(self.m)]
        for i, a in enumerate(actions):
            assert a in self.valid_actions(i), (i, a)
        robot = np.zeros(self.m)
        drops = list(self.pending_drops)
        for k, task in enumerate(self.slots):  # step 5
            bidders = [i for i in range(self.m) if actions[i] == k + 1]
            if bidders:
                best = max(self.d[i, task["type"]] for i in bidders)
                w = min(i for i in bidders if self.d[i, task["type"]] == best)
                # spec, task-switch setup cost: another type than the previous task's needs a setup
                switch = self.last_type[w] not in (None, task["type"])
                busy = task["duration"] + (p.switch_ticks if switch else 0)
                self.last_type[w] = task["type"]
                self.busy_until[w] = self.t + busy
                self.battery[w] -= p.drain_per_tick * busy
                if self.battery[w] < p.battery_threshold:
                    self.busy_until[w] += p.charge_ticks
                    self.battery[w] = float(p.battery_capacity)
                robot[w] += p.reward_assign_high if task["high"] else p.reward_assign_low
                self.assigned[task["type"], task["high"]] += 1
                self.queue.remove(task)
            elif task["round"] == 1:  # step 6
                task["round"], task["due"] = 2, self.t + p.reauction_delay
            else:
                drops.append(task)
                self.queue.remove(task)
        for (
            task
        ) in drops:  # step 8: the penalty is shared by the robots whose Lambda holds the type
            self.dropped[task["type"], task["high"]] += 1
            penalty = p.penalty_drop_high if task["high"] else p.penalty_drop_low
            holders = np.flatnonzero(self.active[:, task["type"]])
            robot[holders] -= penalty / len(holders)
        for i in range(self.m):  # step 7
            self.busy_ticks[i] += (not idle[i]) or actions[i] > 0
        self.t += 1
        team = sum(
            (p.reward_assign_high if x["high"] else p.reward_assign_low)
            for k, x in enumerate(self.slots)
            if any(a == k + 1 for a in actions)
        ) - sum(p.penalty_drop_high if x["high"] else p.penalty_drop_low for x in drops)
        if self.t < p.horizon:
            self.start_tick()
        else:
            self.slots = []
        return team, robot
