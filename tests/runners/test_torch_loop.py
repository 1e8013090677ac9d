"""The one torch loop: families of teams, its buffers, and a torch learner from a user module."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra.core.hydra_config import HydraConfig
from tensordict import TensorDict

from mrta_rl.config import ConfigError
from mrta_rl.learners.neural.torch_learner import LoopSettings
from mrta_rl.runners import torch_loop, train
from mrta_rl.runners.checkpoint import TrainingCheckpoint
from mrta_rl.runners.replay import LoopBuffer
from tests.runners.test_checkpoint import save_hydra_files

ROOT = Path(__file__).resolve().parents[2]
# the torch learners whose settings fit any team
ANY_TEAM = [
    ["learner=ippo"],
    ["learner=vdn", "learner.network=set"],
    ["learner=iql", "learner.network=set"],
    ["learner=expert_iteration", "learner.samples=2", "learner.horizon=4"],
]


@pytest.fixture
def teams_played(monkeypatch) -> list:
    """The teams the torch loop binds its learner to, episode by episode."""
    played = []
    family_env = torch_loop.family_env

    def spy(run, episode, seed):
        env = family_env(run, episode, seed)
        played.append((episode, env.system.name, env.n_robots, env.n_task_types))
        return env

    monkeypatch.setattr(torch_loop, "family_env", spy)
    return played


@pytest.mark.parametrize("learner", ANY_TEAM, ids=lambda a: " ".join(a))
def test_a_torch_learner_that_fits_any_team_trains_on_a_family_playing_other_teams(
    compose_cfg, tmp_path, teams_played, learner
):
    args = [*learner, "system=family", "debug=smoke", "train.episodes=3"]
    metrics = train(compose_cfg(args), run_dir=tmp_path)
    assert [episode for episode, *_ in teams_played] == [1, 2, 3]
    teams = {tuple(team) for _, *team in teams_played}
    assert len(teams) == 3  # three teams of the family, of other sizes
    assert len({robots for _, _, robots, _ in teams_played}) > 1
    assert metrics["train"]["episodes"] == 3 and metrics["train"]["gradient_steps"] > 0
    assert metrics["system"] == "family"  # evaluated on the family's evaluation team


def test_a_student_of_a_family_plans_on_a_trained_family_base(compose_cfg, tmp_path, teams_played):
    """The teacher's base, a net_es run of the family, plays each new team without being trained
    on it: its training batch (2 * pairs copies) is not the student's, and the student's copies
    stay the student's."""
    base_args = ["learner=net_es", "system=family", "debug=smoke", "train.episodes=1"]
    base_cfg = compose_cfg([*base_args, "learner.pairs=3", "train.batch_size=6"])
    train(base_cfg, run_dir=tmp_path / "base")
    save_hydra_files(base_cfg, tmp_path / "base", "net_es", "family")
    teams_played.clear()
    student = [*ANY_TEAM[3], f"learner.base={tmp_path / 'base'}", "system=family"]
    args = [*student, "debug=smoke", "train.episodes=2", "train.batch_size=4"]  # not 6's multiple
    student_cfg = compose_cfg(args)
    metrics = train(student_cfg, tmp_path / "run")
    assert [episode for episode, *_ in teams_played] == [1, 2]
    assert metrics["train"]["episodes"] == 2 and metrics["train"]["gradient_steps"] > 0
    # zero-shot on System-I: the student and its family base both play a team neither trained on
    save_hydra_files(student_cfg, tmp_path / "run", "expert_iteration", "family")
    zero_shot = [*ANY_TEAM[3], f"learner.base={tmp_path / 'base'}", "system=system1"]
    zero_shot += ["debug=smoke", "train.episodes=0", f"init={tmp_path / 'run'}"]
    played = train(compose_cfg(zero_shot), tmp_path / "zero_shot")
    assert played["system"] == "system1" and played["eval"]["team_return"]["mean"] > 0


@pytest.mark.parametrize("learner", ["qmix", "mappo", "subg_dqn"])
def test_a_torch_learner_tied_to_one_team_is_refused_on_a_family(compose_cfg, tmp_path, learner):
    with pytest.raises(ConfigError, match=r"tied to one team's robots.*learners that can:.*ippo"):
        train(compose_cfg([f"learner={learner}", "system=family", "debug=smoke"]), tmp_path)
    assert not tmp_path.joinpath("metrics.json").exists()


def test_a_batch_that_would_straddle_two_teams_is_refused(compose_cfg, tmp_path):
    """smoke: 50 ticks x 4 copies = 200 frames an episode; 120 frames do not divide it."""
    args = ["learner=ippo", "system=family", "debug=smoke", "learner.frames_per_batch=120"]
    with pytest.raises(ConfigError, match=r"batch of 120 frames does not divide an episode"):
        train(compose_cfg(args), run_dir=tmp_path)


@pytest.mark.parametrize("learner", ANY_TEAM[:2], ids=lambda a: " ".join(a))
def test_a_family_run_stopped_and_resumed_ends_as_the_uninterrupted_one(
    compose_cfg, tmp_path, monkeypatch, learner
):
    """Stopped after episode 2 of 4 (its buffer holds two teams), resumed in the same process:
    the same evaluation and weights as the run that was never stopped."""
    args = [*learner, "system=family", "debug=smoke", "train.episodes=4"]
    args += ["train.checkpoint_every=1"]
    full = train(compose_cfg(args), run_dir=tmp_path / "full")
    resumed = stopped_after_two_and_resumed(compose_cfg, monkeypatch, args, tmp_path / "cut")
    assert resumed["eval"] == full["eval"]
    assert_same_weights(tmp_path / "full", tmp_path / "cut")


def stopped_after_two_and_resumed(compose_cfg, monkeypatch, args: list[str], cut: Path) -> dict:
    """Train ``args`` in ``cut``, stopped after episode 2 (as by Ctrl-C), then resume it."""
    episode_end = TrainingCheckpoint.episode_end

    def stop_after_two(self, loop, last, files=None):
        self.stop_requested = self.stop_requested or loop["episode"] >= 2
        return episode_end(self, loop, last, files)

    monkeypatch.setattr(TrainingCheckpoint, "episode_end", stop_after_two)
    cfg = compose_cfg(args)
    system = next(a.split("=")[1] for a in args if a.startswith("system="))
    save_hydra_files(cfg, cut, args[0].split("=")[1], system)
    with pytest.raises(SystemExit):
        train(cfg, run_dir=cut)
    monkeypatch.setattr(TrainingCheckpoint, "episode_end", episode_end)
    cfg = compose_cfg([f"resume={cut}"])
    HydraConfig.instance().cfg = None  # as from the command line: no overrides but resume=
    return train(cfg)


def assert_same_weights(a: Path, b: Path) -> None:
    weights = [torch.load(run / "learner" / "weights.pt", weights_only=True) for run in (a, b)]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_a_family_buffer_keeps_the_newest_teams_that_fit_and_samples_each_team_alone():
    settings = LoopSettings(
        4, buffer_size=10, minibatch_size=3, updates_per_batch=1, warmup_frames=0
    )
    buffer = LoopBuffer(settings, on_policy=False, device=torch.device("cpu"), episode_frames=4)
    for episode, width in ((1, 2), (2, 3), (3, 5)):  # each team's rows have their own shape
        rows = TensorDict({"x": torch.full((4, width), float(episode))}, [4])
        buffer.extend(rows, str(episode))
        assert buffer.expected(4 * episode, episode, family=True) == {
            team: (len(b), buffer.written[team]) for team, b in buffer.buffers.items()
        }
    assert list(buffer.buffers) == ["2", "3"] and len(buffer) == 8  # team 1 left: 12 > 10
    torch.manual_seed(0)
    drawn = {int(buffer.sample()["x"][0, 0]) for _ in range(50)}
    assert drawn == {2, 3}  # a minibatch is one team's, and both are drawn


def test_an_on_policy_buffer_takes_each_epoch_in_one_permutation():
    """The sampler draws an epoch's order when the epoch starts, as torch.randperm per epoch."""
    settings = LoopSettings(
        6, buffer_size=6, minibatch_size=3, updates_per_batch=4, warmup_frames=0
    )
    buffer = LoopBuffer(settings, on_policy=True, device=torch.device("cpu"), episode_frames=6)
    buffer.extend(TensorDict({"x": torch.arange(6.0)}, [6]))
    torch.manual_seed(1)
    rows = [buffer.sample()["x"].tolist() for _ in range(4)]
    torch.manual_seed(1)
    orders = [torch.randperm(6).tolist() for _ in range(2)]
    assert rows == [orders[0][:3], orders[0][3:], orders[1][:3], orders[1][3:]]
    after = torch.rand(1)
    torch.manual_seed(1)
    [torch.randperm(6) for _ in range(2)]
    assert torch.equal(after, torch.rand(1))  # no third order drawn


@pytest.mark.parametrize("system", ["system1", "family"])
def test_validation_during_training_is_logged_and_changes_nothing(compose_cfg, tmp_path, system):
    """Validating every episode logs the validation return and trains as a run without it.

    The evaluations play an env of their own on the validation streams (a family's: its
    evaluation team), so the weights and the curve end bit for bit as without them; the
    logged value is the greedy policy's return on those streams, as re-evaluation gives it.
    """
    args = ["learner=vdn", "learner.network=set", f"system={system}", "debug=smoke"]
    args += ["train.episodes=3", "train.validate_episodes=4"]
    plain = train(compose_cfg(args), run_dir=tmp_path / "plain")
    validated = train(compose_cfg([*args, "train.validate_every=1"]), run_dir=tmp_path / "val")
    assert validated["eval"] == plain["eval"]
    for name in ("curve.csv", "learner/weights.pt"):
        assert (tmp_path / "val" / name).read_bytes() == (tmp_path / "plain" / name).read_bytes()
    logged = tmp_path / "val" / "torchrl" / "train" / "scalars" / "val" / "team_return.csv"
    values = [float(line.split(",")[1]) for line in logged.read_text().splitlines()]
    assert len(values) == 3
    evaluate = ["eval.split=validation", "eval.episodes=4", "eval.batch_size=4"]
    again = train(compose_cfg([*args, "train.validate_every=3", *evaluate]), tmp_path / "again")
    assert values[-1] == pytest.approx(again["eval"]["team_return"]["mean"], abs=1e-9)
    assert not (tmp_path / "plain" / "torchrl" / "train" / "scalars" / "val").exists()


def test_validation_during_training_is_the_torch_loops(compose_cfg, tmp_path):
    with pytest.raises(ConfigError, match=r"train.validate_every: the torch loop's; DQL"):
        train(compose_cfg(["learner=dql", "debug=smoke", "train.validate_every=1"]), tmp_path)


def test_keep_best_ends_with_the_snapshot_of_the_best_validation_return(compose_cfg, tmp_path):
    """Validated every episode, the run keeps the weights of its best validation return.

    Its evaluation on the same validation streams gives that return again, its metrics name the
    episode kept, and the value is the largest one logged.
    """
    validate = ["train.validate_every=1", "train.validate_episodes=4", "train.keep_best=true"]
    streams = ["eval.split=validation", "eval.episodes=4", "eval.batch_size=4"]
    args = ["learner=vdn", "system=system1", "debug=smoke", "train.episodes=4"]
    metrics = train(compose_cfg([*args, *validate, *streams]), run_dir=tmp_path)
    logged = tmp_path / "torchrl" / "train" / "scalars" / "val" / "team_return.csv"
    values = [float(line.split(",")[1]) for line in logged.read_text().splitlines()]
    best = max(values)
    assert metrics["train"]["best_episode"] == values.index(best) + 1
    assert metrics["train"]["best_validation_return"] == pytest.approx(best, abs=1e-3)
    assert metrics["eval"]["team_return"]["mean"] == pytest.approx(best, abs=1e-9)


def test_keep_best_resumes_with_its_snapshot(compose_cfg, tmp_path, monkeypatch):
    """Stopped after episode 2 of 4 and resumed: the same snapshot kept as without the stop."""
    args = ["learner=vdn", "system=system1", "debug=smoke", "train.episodes=4"]
    args += ["train.checkpoint_every=1", "train.validate_every=1", "train.validate_episodes=3"]
    args += ["train.keep_best=true"]
    full = train(compose_cfg(args), run_dir=tmp_path / "full")
    resumed = stopped_after_two_and_resumed(compose_cfg, monkeypatch, args, tmp_path / "cut")
    assert resumed["eval"] == full["eval"]
    assert resumed["train"]["best_episode"] == full["train"]["best_episode"]
    assert_same_weights(tmp_path / "full", tmp_path / "cut")


def test_keep_best_needs_validation(compose_cfg, tmp_path):
    with pytest.raises(ConfigError, match=r"train.keep_best: .*train.validate_every > 0"):
        train(compose_cfg(["learner=vdn", "debug=smoke", "train.keep_best=true"]), tmp_path)
