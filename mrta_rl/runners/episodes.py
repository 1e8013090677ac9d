"""Episode accounting of the torch loop: team returns of collected batches, curve rows.

The torch loop (``runners/torch_loop.py``), on-policy and off-policy alike, collects ``[B, T]``
batches of whole ticks of every copy; the copies share the horizon, so they
finish their episodes together, and an episode's row in curve.csv is the copies' mean team return.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase


class EpisodeReturns:
    """Running team return per copy over collected batches; one curve row per finished episode.

    Args:
        batch: ``B``, the training copies.
        team_group: A group of the env view: its ``(group, "reward")`` is the team reward.
        episodes: Episodes finished before (a resumed run).
    """

    def __init__(self, batch: int, team_group: str, episodes: int = 0) -> None:
        self.batch = batch
        self.team_group = team_group
        self.episodes = episodes
        self.running = torch.zeros(batch)  # [B] team return of the current episode, per copy
        self.recent = "-"  # last episode's mean team return, for the progress bar

    def add(self, data: TensorDictBase, frames: int) -> tuple[list[dict[str, Any]], bool]:
        """Count a collected batch.

        Args:
            data: ``[B, T]`` collector output.
            frames: Frames collected before this batch.

        Returns:
            ``(rows, boundary)``: the curve rows of the episodes it finished (``env_ticks``,
            ``episode``, ``team_return_mean``) and whether it ends between episodes (every copy
            done at its last tick: a training checkpoint may be taken there).
        """
        # [B, T] team reward: every group's (group, "reward") is the team reward, per robot
        reward = data.get(("next", self.team_group, "reward"))[..., 0, 0]
        reward = reward.reshape(self.batch, -1).cpu()
        done = data.get(("next", "done")).reshape(self.batch, -1).cpu()  # [B, T]
        rows = []
        for t in range(reward.shape[1]):
            self.running += reward[:, t]
            if done[:, t].all():  # copies share the horizon: they finish together
                self.episodes += 1
                team_return = float(self.running.mean())
                self.recent = f"{team_return:.1f}"
                rows.append(
                    {
                        "env_ticks": frames + (t + 1) * self.batch,
                        "episode": self.episodes,
                        "team_return_mean": team_return,
                    }
                )
                self.running.zero_()
        return rows, bool(done[:, -1].all())
