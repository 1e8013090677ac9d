"""Every yaml of every config group composes, and builds (system, params, env, learner, logger)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.errors import MissingConfigException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from mrta_rl.config import ConfigError
from mrta_rl.partition import subg_partition
from mrta_rl.runners import build_run, validate_config
from mrta_rl.runners.validation import check_evaluate_config
from mrta_rl.systems import build_system

CONF = Path(__file__).resolve().parents[1] / "conf"
GROUP_FILES = sorted(
    (group.name, path.stem)
    for group in CONF.iterdir()
    if group.is_dir()
    for path in group.glob("*.yaml")
)
PRIMARY = sorted(path.stem for path in CONF.glob("*.yaml"))
# groups that conf/config.yaml does not list (budget: pulled in by the neural learners' yamls)
# are added with "+"
LISTED = {
    next(iter(entry))
    for entry in OmegaConf.load(CONF / "config.yaml").defaults
    if entry != "_self_"
}


@pytest.mark.parametrize(("group", "name"), GROUP_FILES, ids=[f"{g}/{n}" for g, n in GROUP_FILES])
def test_group_file_builds(group, name, compose_cfg, tmp_path):
    overrides = [f"{group}={name}" if group in LISTED else f"+{group}={name}"]
    if group != "debug":
        overrides.append("debug=smoke")  # keeps envs small (horizon, batches)
    cfg = compose_cfg(overrides)
    run = build_run(cfg)  # validates system, env params, partition and learner construction
    instantiate(cfg.logger)(run_dir=tmp_path).close()
    actions = run.learner.act(run.learner.encode(run.env), run.env.action_mask, explore=False)
    assert actions.shape == (run.env.batch_size, run.env.n_robots)
    assert np.take_along_axis(run.env.action_mask, actions[..., None], axis=2).all()


def default_choice(group: str, config_name: str) -> str:
    """The option of ``group`` that ``conf/<config_name>.yaml`` lists in its defaults."""
    entries = OmegaConf.load(CONF / f"{config_name}.yaml").defaults
    return next(
        entry[group] for entry in entries if isinstance(entry, DictConfig) and group in entry
    )


def test_every_primary_config_is_tested_below():
    # a config file added next to config.yaml gets a test of what its command reads
    assert PRIMARY == ["config", "evaluate", "partition"]


def test_the_train_config_is_a_valid_run_of_its_default_learner_and_system(compose_cfg):
    learner, system = default_choice("learner", "config"), default_choice("system", "config")
    checked = validate_config(compose_cfg([f"learner={learner}"]))
    target = OmegaConf.load(CONF / "learner" / f"{learner}.yaml")._target_
    assert f"{checked.learner_cls.__module__}.{checked.learner_cls.__name__}" == target
    expected = build_system(yaml.safe_load((CONF / "system" / f"{system}.yaml").read_text()))
    assert (checked.system.name, checked.system.robots) == (expected.name, expected.robots)
    np.testing.assert_array_equal(checked.system.willingness, expected.willingness)
    # the run writes its own dir and config snapshot
    assert HydraConfig.get().output_subdir == ".hydra"
    assert HydraConfig.get().run.dir.startswith("outputs/")


def test_the_evaluate_config_reads_a_checkpoint_and_writes_no_run_dir(compose_cfg):
    cfg = compose_cfg(["checkpoint=somewhere"], config_name="evaluate")
    args = {"checkpoint": "somewhere", "episodes": None, "batch_size": None, "split": None}
    assert check_evaluate_config(cfg) == args
    assert (HydraConfig.get().run.dir, HydraConfig.get().output_subdir) == (".", None)
    with pytest.raises(ConfigError, match="checkpoint: missing"):
        check_evaluate_config(compose_cfg([], config_name="evaluate"))


def test_the_partition_config_partitions_its_default_system(compose_cfg):
    cfg = compose_cfg([], config_name="partition")
    system = default_choice("system", "partition")
    assert cfg.system == OmegaConf.load(CONF / "system" / f"{system}.yaml")
    team = build_system(OmegaConf.to_container(cfg.system))
    partition = subg_partition(team, **cfg.partition)
    # every robot of the team in exactly one sub-group
    assert sorted(r for robots in partition.groups.values() for r in robots) == sorted(team.robots)
    assert cfg.format == "table"
    assert (HydraConfig.get().run.dir, HydraConfig.get().output_subdir) == (".", None)


def test_unknown_learner_is_named(compose_cfg):
    with pytest.raises(MissingConfigException, match="nope"):
        compose_cfg(["learner=nope"])


SPECIALIZED = sorted(
    (path.parent.name, path.stem) for path in (CONF / "experiment_learner").glob("*/*.yaml")
)


DEBUG_SPECIALIZED = sorted(
    (path.parent.name, path.stem) for path in (CONF / "debug_learner").glob("*/*.yaml")
)


@pytest.mark.parametrize(("debug", "learner"), DEBUG_SPECIALIZED)
def test_a_debug_files_own_learner_settings_name_both_and_apply(debug, learner, compose_cfg):
    # a misspelt folder or file would be skipped silently by the `optional` defaults entry
    assert (CONF / "debug" / f"{debug}.yaml").exists()
    assert (CONF / "learner" / f"{learner}.yaml").exists()
    own = OmegaConf.load(CONF / "debug_learner" / debug / f"{learner}.yaml")
    cfg = compose_cfg([f"debug={debug}", f"learner={learner}"])
    assert {key: cfg.learner[key] for key in own} == dict(own)
    plain = compose_cfg([f"learner={learner}"])  # without the debug file: the learner's own
    assert {key: plain.learner[key] for key in own} != dict(own)


@pytest.mark.parametrize(("experiment", "learner"), SPECIALIZED)
def test_an_experiments_own_learner_settings_name_both_and_build(experiment, learner, compose_cfg):
    # a misspelt folder or file would be skipped silently by the `optional` defaults entry
    assert (CONF / "experiment" / f"{experiment}.yaml").exists()
    assert (CONF / "learner" / f"{learner}.yaml").exists()
    cfg = compose_cfg([f"experiment={experiment}", f"learner={learner}", "debug=smoke"])
    own = OmegaConf.load(CONF / "experiment_learner" / experiment / f"{learner}.yaml")
    own.pop("defaults", None)  # what the file pulls in elsewhere (a budget), not learner keys
    assert {key: cfg.learner[key] for key in own} == dict(own)
    build_run(cfg)


def test_the_paper_experiment_runs_the_papers_semi_cql_and_nothing_else_changes(compose_cfg):
    # paper §6's semi-CQL learns over the whole-system state; the learner's own default is coarser
    assert compose_cfg(["learner=semi_cql"]).learner.state == "slots"
    paper = compose_cfg(["experiment=paper", "learner=semi_cql"]).learner
    assert (paper.state, paper.min_visits) == ("system", 5)
    # the command line still wins over the experiment's settings
    assert (
        compose_cfg(["experiment=paper", "learner=semi_cql", "learner.min_visits=7"]).learner[
            "min_visits"
        ]
        == 7
    )
    # other learners and other experiments keep their own yaml
    assert (
        compose_cfg(["experiment=paper", "learner=cql"]).learner
        == compose_cfg(["learner=cql"]).learner
    )
    assert compose_cfg(["experiment=yardsticks", "learner=semi_cql"]).learner.state == "slots"
    # paper §6's subG-CQL: the paper's group state at the tabular budget (30 episodes x 16
    # copies); the learner's defaults are the coarse `idle` state with time_to_free at 512 copies
    default = compose_cfg(["learner=subg_cql"])
    assert (default.learner.state, default.learner.features) == ("idle", "time_to_free")
    assert (default.train.episodes, default.train.batch_size) == (30, 512)
    paper = compose_cfg(["experiment=paper", "learner=subg_cql"])
    assert (paper.learner.state, paper.learner.features) == ("group", "paper")
    assert (paper.train.episodes, paper.train.batch_size) == (30, 16)
    # the pin is conf/config.yaml's tabular budget, which the paper's other learners run
    tabular = compose_cfg(["experiment=paper", "learner=cql"]).train
    assert (tabular.episodes, tabular.batch_size) == (30, 16)
    # the command line and debug=smoke still win over the pin
    wider = compose_cfg(["experiment=paper", "learner=subg_cql", "train.batch_size=64"])
    assert wider.train.batch_size == 64
    smoke = compose_cfg(["experiment=paper", "learner=subg_cql", "debug=smoke"]).train
    assert (smoke.episodes, smoke.batch_size) == tuple(
        compose_cfg(["experiment=paper", "learner=cql", "debug=smoke"]).train[key]
        for key in ("episodes", "batch_size")
    )
    # other experiments run subG-CQL's own defaults and budget
    yardsticks = compose_cfg(["experiment=yardsticks", "learner=subg_cql"])
    assert (yardsticks.learner.state, yardsticks.train.batch_size) == ("idle", 512)


def test_subg_cqls_copies_are_capped_by_team_size(compose_cfg):
    # conf/budget/subg_cql.yaml: 512 copies, at most 5120 robot-copies per tick (512 x 10 robots)
    for system, copies in [("system1", 512), ("system2", 512)]:  # 5120 // 6 = 853, 5120 // 10 = 512
        cfg = compose_cfg(["learner=subg_cql", f"system={system}"])
        assert (cfg.train.batch_size, cfg.train.robot_copies) == (512, 5120)
        assert build_run(cfg).env.batch_size == copies
    # a 200-robot team: 5120 // 200 = 25 copies
    big = [
        "learner=subg_cql",
        "system=random",
        "system.n_robots=200",
        "system.n_task_types=12",
        "system.density=0.25",
        "system.seed=0",
        "partition.max_group_size=4",
    ]
    assert build_run(compose_cfg(big)).env.batch_size == 25
    assert build_run(compose_cfg([*big, "train.robot_copies=null"])).env.batch_size == 512
    # every other learner, and subG-CQL at the paper's budget, has no cap
    assert compose_cfg(["learner=cql"]).train.robot_copies is None
    assert compose_cfg(["learner=qmix"]).train.robot_copies is None
    paper = compose_cfg(["experiment=paper", "learner=subg_cql"]).train  # conf/budget/tabular.yaml
    assert paper == compose_cfg(["experiment=paper", "learner=cql"]).train  # conf/config.yaml's
