"""AuctionParams: every parameter of the auction dynamics, with the spec's defaults."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

from mrta_rl.config import ConfigError, Range, check_fields


@dataclass(frozen=True)
class AuctionParams:
    """Parameters of the auction environment; field defaults are the spec's table (the one source).

    ``arrival_rate=None`` means the spec default ``m / 6``; :meth:`resolve` fills it in.
    """

    horizon: Annotated[int, Range(1)] = 1000  # ticks per episode (truncation)
    arrival_rate: Annotated[float | None, Range(0)] = None  # Poisson tasks per tick; None: m / 6
    p_high: Annotated[float, Range(0, 1)] = 0.33  # probability that a new task is high-priority
    slots: Annotated[int, Range(1)] = 3  # K: tasks auctioned at the same tick, at most
    queue_capacity: Annotated[int, Range(1)] = 32  # tasks waiting at once, at most (>= slots)
    reauction_delay: Annotated[int, Range(1)] = 3  # ticks from a failed first auction to the 2nd
    battery_capacity: Annotated[float, Range(0, low_open=True)] = 100.0  # battery of a full robot
    drain_per_tick: Annotated[float, Range(0)] = 1.0  # battery used per tick of task execution
    battery_threshold: float = 20.0  # below this after a task, the robot charges
    charge_ticks: Annotated[int, Range(0)] = 10  # length of a charge
    reward_assign_high: float = 10.0  # team reward when an H task is assigned
    reward_assign_low: float = 2.0  # team reward when an L task is assigned
    penalty_drop_high: float = 5.0  # subtracted when an H task is dropped
    penalty_drop_low: float = 0.0  # subtracted when an L task is dropped
    # default duration ranges [lo, hi] of L and H tasks, ends included (lo <= hi)
    duration_low: Annotated[tuple[int, int], Range(1)] = (3, 6)
    duration_high: Annotated[tuple[int, int], Range(1)] = (6, 12)
    # extra busy ticks before a task of another type than the robot's previous one
    # (docs/spec/auction_env.md); 0 = no switch cost
    switch_ticks: Annotated[int, Range(0)] = 0
    # separate auctions the robots bid in (docs/spec/auction_env.md, "Auction zones"): robot i
    # bids only for the slots of its zone; 1 = one auction for the whole team
    zones: Annotated[int, Range(1)] = 1

    def __post_init__(self) -> None:
        # the declarations above are the checks (mrta_rl.config); only relations between
        # fields are written here
        for name, value in check_fields(AuctionParams, self.as_dict(), "AuctionParams").items():
            object.__setattr__(self, name, value)
        relations = {
            "queue_capacity": (self.queue_capacity >= self.slots, "must be >= slots"),
            "zones": (self.zones <= self.slots, "must be <= slots (every zone has a slot)"),
            "duration_low": (self.duration_low[0] <= self.duration_low[1], "needs lo <= hi"),
            "duration_high": (self.duration_high[0] <= self.duration_high[1], "needs lo <= hi"),
        }
        for name, (ok, rule) in relations.items():
            if not ok:
                raise ConfigError(f"AuctionParams.{name}: {rule}, got {getattr(self, name)!r}")

    def as_dict(self) -> dict[str, Any]:
        """The fields as a plain dict (not resolved)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

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
            ConfigError: naming an unknown parameter or a value out of its declaration.
        """
        values: dict[str, Any] = {}
        for layer in layers:
            values.update(check_fields(cls, dict(layer or {}), "env", null_is_default=True))
        return cls(**values)
