"""The Gymnasium ids: which team each plays, and a clear refusal of a missing or other team."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import mrta_rl.envs  # noqa: F401 (registers the ids)
from tests.conftest import CONF, paper_system


def test_the_generic_id_without_a_system_names_the_keyword():
    with pytest.raises(
        ValueError, match=r"mrta_rl/Auction-v0: pass the team as system=\.\.\."
    ) as e:
        gym.make("mrta_rl/Auction-v0")
    assert "system1" in str(e.value) and "a team yaml path" in str(e.value)


@pytest.mark.parametrize(
    ("env_id", "other"),
    [("mrta_rl/Auction-System1-v0", "system2"), ("mrta_rl/Auction-System2-v0", "system1")],
)
def test_a_per_system_id_refuses_another_team(env_id, other):
    with pytest.raises(ValueError, match=f"{env_id} plays .*; system='{other}' is another team"):
        gym.make(env_id, system=other)


def test_a_per_system_id_refuses_a_team_of_the_same_name_with_other_robots():
    team = {"name": "system1", "robots": {"R1": ["T1"], "R2": ["T1", "T2"]}}
    with pytest.raises(ValueError, match="is another team"):
        gym.make("mrta_rl/Auction-System1-v0", system=team)


@pytest.mark.parametrize(
    "same",
    ["system1", str(CONF / "system" / "system1.yaml"), paper_system("system1")],
    ids=["name", "path", "RobotSystem"],
)
def test_a_per_system_id_accepts_its_own_team_however_given(same):
    env = gym.make("mrta_rl/Auction-System1-v0", system=same, params={"horizon": 5})
    reference = gym.make("mrta_rl/Auction-System1-v0", params={"horizon": 5})
    assert env.unwrapped.core.system.robots == paper_system("system1").robots
    obs, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs, reference.reset(seed=3)[0])
