"""Counter-based draws: every (copy seed, episode) pair draws its own task stream."""

from __future__ import annotations

import numpy as np

from mrta_rl.envs import counter_rng as rng


def test_episode_keys_distinct_over_copies_and_episodes():
    # a symmetric mix of (copy seed, episode) would give copy b's episode e the task stream of
    # copy e's episode b: the training copies of one run would repeat each other's streams
    seeds = np.arange(200)
    keys = rng.seed_keys(seeds)
    grid = np.stack([rng.episode_keys(keys, np.full(len(seeds), e)) for e in range(200)])
    assert len(np.unique(grid)) == grid.size  # 40,000 pairs, pairwise distinct
    assert grid[3, 5] != grid[5, 3]


def test_tick_streams_distinct_over_copies_and_episodes():
    # the first ticks' arrival draws differ between pairs, not only the keys
    seeds = np.arange(32)
    keys = rng.seed_keys(seeds)
    streams = set()
    for e in range(32):
        ek = rng.episode_keys(keys, np.full(len(seeds), e))
        draws = np.stack(
            [rng.unit_float(rng.tick_keys(ek, np.full(len(seeds), t))) for t in range(8)]
        )
        streams.update(map(tuple, draws.T.round(12)))
    assert len(streams) == 32 * 32


def test_training_copies_of_seed_zero_draw_distinct_episodes():
    # the default run: seed 0, 16 copies x 30 episodes = 480 copy-episodes, all distinct
    keys = rng.seed_keys(np.arange(16))
    grid = np.stack([rng.episode_keys(keys, np.full(16, e)) for e in range(30)])
    assert len(np.unique(grid)) == 480
