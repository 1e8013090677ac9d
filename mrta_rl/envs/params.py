"""AuctionParams: every parameter of the auction dynamics, with the spec's defaults."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class AuctionParams:
    """Parameters of the auction environment; field defaults are the spec's table (the one source).

    ``arrival_rate=None`` means the spec default ``m / 6``; :meth:`resolve` fills it in.
    """

    horizon: int = 1000  # ticks per episode (truncation)
    arrival_rate: float | None = None  # Poisson mean of new tasks per tick; None -> m / 6
    p_high: float = 0.33  # probability that a new task is high-priority
    slots: int = 3  # K: tasks auctioned at the same tick, at most
    queue_capacity: int = 32  # tasks waiting at once, at most
    reauction_delay: int = 3  # ticks between a failed first auction and the second
    battery_capacity: float = 100.0  # battery of a full robot
    drain_per_tick: float = 1.0  # battery used per tick of task execution
    battery_threshold: float = 20.0  # below this after a task, the robot charges
    charge_ticks: int = 10  # length of a charge
    reward_assign_high: float = 10.0  # team reward when an H task is assigned
    reward_assign_low: float = 2.0  # team reward when an L task is assigned
    penalty_drop_high: float = 5.0  # subtracted when an H task is dropped
    penalty_drop_low: float = 0.0  # subtracted when an L task is dropped
    duration_low: tuple[int, int] = (3, 6)  # default duration range of L tasks, ends included
    duration_high: tuple[int, int] = (6, 12)  # default duration range of H tasks, ends included
    # extra busy ticks before a task of another type than the robot's previous one (issue 11;
    # docs/spec/auction_env.md); 0 = no switch cost
    switch_ticks: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "duration_low", tuple(int(x) for x in self.duration_low))
        object.__setattr__(self, "duration_high", tuple(int(x) for x in self.duration_high))
        checks = {
            "horizon": self.horizon >= 1,
            "arrival_rate": self.arrival_rate is None or self.arrival_rate >= 0,
            "p_high": 0.0 <= self.p_high <= 1.0,
            "slots": self.slots >= 1,
            "queue_capacity": self.queue_capacity >= self.slots,
            "reauction_delay": self.reauction_delay >= 1,
            "battery_capacity": self.battery_capacity > 0,
            "drain_per_tick": self.drain_per_tick >= 0,
            "charge_ticks": self.charge_ticks >= 0,
            "switch_ticks": self.switch_ticks >= 0,
            "duration_low": len(self.duration_low) == 2
            and 1 <= self.duration_low[0] <= self.duration_low[1],
            "duration_high": len(self.duration_high) == 2
            and 1 <= self.duration_high[0] <= self.duration_high[1],
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ValueError(
                f"AuctionParams: invalid value for {bad}: "
                + ", ".join(f"{b}={getattr(self, b)!r}" for b in bad)
            )

    def resolve(self, n_robots: int) -> AuctionParams:
        """Fill the defaults that depend on the system (arrival_rate = m / 6)."""
        if self.arrival_rate is not None:
            return self
        return dataclasses.replace(self, arrival_rate=n_robots / 6.0)

    @classmethod
    def merged(cls, *layers: Mapping[str, Any] | None) -> AuctionParams:
        """Build params from layers of overrides, later layers winning; ``None`` values are skipped.

        The usual order is ``(system.env_overrides, cfg.env)``: the spec defaults, then the system
        file's ``env:`` block, then the run's ``env.*`` settings.

        Raises:
            ValueError: naming an unknown parameter.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        values: dict[str, Any] = {}
        for layer in layers:
            for key, value in dict(layer or {}).items():
                if key not in names:
                    raise ValueError(
                        f"unknown environment parameter {key!r}; known: {sorted(names)}"
                    )
                if value is not None:
                    values[key] = tuple(value) if key.startswith("duration_") else value
        return cls(**values)
