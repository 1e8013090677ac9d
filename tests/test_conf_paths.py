"""Shipped configs and team files: a system by name or by path, one message when there is none."""

from __future__ import annotations

import pytest
from hydra.core.config_store import ConfigStore

from mrta_rl.commands import use_team_files
from mrta_rl.conf_paths import conf_dir, system_file
from mrta_rl.config import UserError
from mrta_rl.envs.view_inputs import resolve_system

TEAM = "name: my_team\nrobots:\n  R1: [T1, T2]\n  R2: [T2]\n"


def test_system_by_name_or_path(tmp_path, monkeypatch):
    assert system_file("system1") == conf_dir() / "system" / "system1.yaml"
    (tmp_path / "my_team.yaml").write_text(TEAM)
    monkeypatch.chdir(tmp_path)
    assert system_file("my_team.yaml") == tmp_path / "my_team.yaml"  # relative to the cwd
    assert resolve_system(tmp_path / "my_team.yaml").n_robots == 2
    for missing in ("system9", "nope.yaml", str(tmp_path / "nope.yml")):
        known = r"unknown system .*known: \['family', 'random', 'system1'"
        with pytest.raises(UserError, match=known):
            system_file(missing)


def test_team_files_become_hydra_systems(tmp_path):
    team = tmp_path / "my_team.yaml"
    team.write_text(TEAM)
    argv = ["mrta-train", "learner=greedy", f"system=system1,{team}", "seed=1"]
    assert use_team_files(argv) == [
        "mrta-train",
        "learner=greedy",
        "system=system1,my_team",
        "seed=1",
    ]
    assert ConfigStore.instance().load("system/my_team.yaml").node.robots.R2 == ["T2"]


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("system1.yaml", TEAM, "the file name 'system1' is taken by a shipped system"),
        ("bad.yaml", "name: bad\nrobots:\n  R1: []\n", r"bad.yaml: robot R1 has no task type"),
        ("gone.yaml", None, "unknown system '.*gone.yaml': no file"),
    ],
)
def test_bad_team_files_are_refused(tmp_path, name, content, message):
    if content is not None:
        (tmp_path / name).write_text(content)
    with pytest.raises(UserError, match=message):
        use_team_files(["mrta-train", f"system={tmp_path / name}"])


def test_two_team_files_of_one_name_are_refused(tmp_path):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "team.yaml").write_text(TEAM)
    with pytest.raises(UserError, match="the file name 'team' is taken by .*a/team.yaml"):
        use_team_files([f"system={tmp_path / 'a' / 'team.yaml'},{tmp_path / 'b' / 'team.yaml'}"])


@pytest.fixture
def benchmarl_task(monkeypatch):
    """``AuctionTask`` over a stand-in of BenchMARL's ``TaskClass`` (BenchMARL has its own venv)."""
    import importlib
    import sys
    import types

    class TaskClass:  # BenchMARL 1.5's constructor: name and config kept as attributes
        def __init__(self, name, config):
            self.name, self.config = name, config

    for name in ("benchmarl", "benchmarl.environments", "benchmarl.environments.common"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    sys.modules["benchmarl.environments.common"].TaskClass = TaskClass
    monkeypatch.delitem(sys.modules, "mrta_rl.envs.benchmarl_task", raising=False)
    yield importlib.import_module("mrta_rl.envs.benchmarl_task").AuctionTask
    sys.modules.pop("mrta_rl.envs.benchmarl_task", None)


def test_benchmarl_task_takes_a_team_file(benchmarl_task, tmp_path):
    team = tmp_path / "my_team.yaml"
    team.write_text(TEAM)
    task = benchmarl_task(config={"system": str(team), "horizon": 5})
    env = task.get_env_fun(num_envs=2, continuous_actions=False, seed=0, device="cpu")()
    assert env.group_map == {"agents": ["R1", "R2"]}
    with pytest.raises(UserError, match="unknown system 'system9': no file .*known: "):
        benchmarl_task(config={"system": "system9"})
    (tmp_path / "bad.yaml").write_text("name: bad\nrobots:\n  R1: []\n")
    with pytest.raises(UserError, match="robot R1 has no task type"):
        benchmarl_task(config={"system": str(tmp_path / "bad.yaml")})


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("name: b\na: &a [T1]\nrobots: {R1: *a}\n", "YAML aliases"),
        ("name: n\nrobots: " + "[" * 100 + "]" * 100 + "\n", "nested deeper"),
    ],
)
def test_a_hostile_team_file_is_refused_before_it_is_read(tmp_path, content, message):
    """A team path goes through the same bounded reader as the shipped configs."""
    path = tmp_path / "team.yaml"
    path.write_text(content)
    with pytest.raises(UserError, match=message):
        system_file(path)
    with pytest.raises(UserError, match=message):
        resolve_system(str(path))
