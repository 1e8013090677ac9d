"""One declaration per parameter, checked before any work, and a fuzz test.

The fuzz test throws random malformed overrides and system files at the
validation layer (``runners/validation.py``): each is either accepted and then plays a smoke
episode, or refused with a :class:`~mrta_rl.config.ConfigError` naming the key or culprit; any
other exception fails the test. ``tests/commands/test_cli.py`` sends a few through the real script.
"""

from __future__ import annotations

import copy
import math
import typing
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf, open_dict

from mrta_rl.config import ConfigError, declared_fields, declared_keywords, is_checked
from mrta_rl.envs import AuctionParams
from mrta_rl.runners import build_run, validate_config
from mrta_rl.runners.validation import (
    EvalSettings,
    LimitSettings,
    TrainSettings,
    learner_class,
    training_copies,
)

ROOT = Path(__file__).resolve().parents[2]
LEARNERS = sorted(p.stem for p in (ROOT / "conf" / "learner").glob("*.yaml"))


# ------------------------------------------------------------------ named refusals
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["learner=qmix", "learner.target_update=foo"], "learner.target_update: must be one of"),
        (["learner=subg_cql", "learner.alpha_power=-2"], r"learner.alpha_power: must be .* >= 0"),
        (["learner=cql", "learner.alpha_min=-5"], r"learner.alpha_min: must be .*\[0, 1\]"),
        (["learner=dql", "learner.epsilon_decay_episodes=-1"], "learner.epsilon_decay_episodes"),
        (["learner=semi_cql", "learner.decisions_only=maybe"], "learner.decisions_only: must be"),
        (["learner=greedy", "env.horizon=10.5"], "env.horizon: must be an integer >= 1, got 10.5"),
        (["learner=vdn", "learner.loss_function=foo"], "learner.loss_function: must be one of"),
        (["learner=subg_cql", "learner.alpha=fast"], "learner.alpha: must be a number"),
        (["learner=greedy", "env.horizon=abc"], "env.horizon: must be an integer >= 1, got 'abc'"),
        (["learner=dql", f"learner.alpha={'1' * 400}"], r"learner.alpha: must be a number in"),
        (["learner=greedy", f"train.episodes={2**63}"], r"train.episodes: .* 64 bits hold\)"),
    ],
)
def test_nonsense_hyperparameters_are_refused_naming_the_key(overrides, message, compose_cfg):
    """Each nonsense value is refused before the run is built, with the key in the message."""
    cfg = compose_cfg([*overrides, "system=system1", "debug=smoke"])
    with pytest.raises(ValueError, match=message):
        build_run(cfg)


def test_every_learner_parameter_is_declared_and_its_yaml_is_valid(compose_cfg):
    """Every hyperparameter of every conf/learner file has a checked type; the files pass."""
    for name in LEARNERS:
        cfg = compose_cfg([f"learner={name}", "system=system1", "debug=smoke"])
        cls = learner_class(cfg.learner)
        declared = declared_keywords(cls)
        undeclared = [k for k, d in declared.items() if not is_checked(d.annotation)]
        assert not undeclared, f"{name}: {undeclared} have no checked type"
        yaml_keys = set(cfg.learner) - {"_target_", "_partial_"}
        assert yaml_keys <= set(declared), name
        validate_config(cfg)
    for dataclass in (AuctionParams, TrainSettings, EvalSettings, LimitSettings):
        assert all(is_checked(d.annotation) for d in declared_fields(dataclass).values())


def test_run_level_keys_are_checked(compose_cfg):
    base = ["learner=greedy", "system=system1", "debug=smoke"]
    for override, message in [
        ("seed=-1", r"seed: must be an integer in \[0, 2147483647\], got -1"),
        ("train.batch_size=0", "train.batch_size: must be an integer >= 1, got 0"),
        ("train.progress_bar=sometimes", "train.progress_bar: must be true or false"),
        ("eval.seed=4294967295", "eval.seed: must be <= 2\\*\\*32 - eval.batch_size"),
        ("limits.memory_gb=0", "limits.memory_gb: must be a number > 0 or null, got 0"),
        ("+train.episodez=3", "train.episodez: unknown setting of TrainSettings"),
        ("~train.episodes", "train.episodes: missing"),
        ("+learner.alpha=${oops}", "learner: "),
    ]:
        with pytest.raises(ConfigError, match=message):
            validate_config(compose_cfg([*base, override]))


def test_robot_copies_cap_the_training_copies_by_team_size():
    # 5120 robot-copies = 512 copies x System-II's 10 robots (conf/budget/subg_cql.yaml)
    assert training_copies(512, 5120, 10) == 512  # System-II: 5120 // 10 = 512
    assert training_copies(512, 5120, 6) == 512  # System-I: 5120 // 6 = 853, B stays 512
    assert training_copies(512, 5120, 200) == 25  # 5120 // 200 = 25.6 -> 25
    assert training_copies(16, 5120, 200) == 16  # the cap never raises B
    assert training_copies(512, 100, 200) == 1  # 100 // 200 = 0 -> at least one copy
    assert training_copies(512, None, 200) == 512  # null: no cap


@pytest.mark.parametrize("value", ["0", "-5", "2.5", "abc", "true"])
def test_bad_robot_copies_are_refused_naming_the_key(value, compose_cfg):
    cfg = compose_cfg(
        ["learner=subg_cql", "system=system1", "debug=smoke", f"train.robot_copies={value}"]
    )
    with pytest.raises(ConfigError, match="train.robot_copies: must be an integer >= 1 or null"):
        validate_config(cfg)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["learner=qmix", "learner.eps_start=0.1", "learner.eps_end=0.5"], "learner.eps_end: 0.5"),
        (["learner=vdn", "learner.prior_in_state=true"], "learner.prior_in_state: needs prior"),
        (["learner=mappo", "learner.frames_per_batch=25"], "learner.frames_per_batch=25 is not"),
        (["learner=ippo", "learner.minibatch_size=5000"], "learner.minibatch_size=5000 is"),
        (["learner=reserve_es", "learner.pairs=5"], "multiple of 2 \\* pairs = 10"),
        (["learner=qmix", "learner.network=set", "learner.max_task_types=2"], "max_task_types"),
    ],
)
def test_settings_that_contradict_each_other_or_the_team_are_refused_before_building(
    overrides, message, compose_cfg
):
    """``validate_config`` refuses them (``Learner.check_settings``) before anything is built."""
    cfg = compose_cfg([*overrides, "system=system1", "debug=smoke"])
    with pytest.raises(ConfigError, match=message):
        validate_config(cfg)


def test_system_env_block_is_checked_with_its_own_key(compose_cfg):
    cfg = compose_cfg(["learner=greedy", "debug=smoke"])
    with open_dict(cfg):
        cfg.system = OmegaConf.create({"name": "s", "robots": {"R1": ["T1"]}, "env": {"slots": 0}})
    with pytest.raises(ConfigError, match="system.env.slots: must be an integer >= 1, got 0"):
        validate_config(cfg)


def test_learners_built_in_python_are_checked_too(tiny_system, rng):
    from mrta_rl.envs import AuctionEnv
    from mrta_rl.learners.tabular.dql import DQLLearner

    with pytest.raises(ConfigError, match=r"DQLLearner.alpha: must be a number in \(0, 1\]"):
        DQLLearner(env=AuctionEnv(tiny_system), rng=rng, alpha=0)
    with pytest.raises(ConfigError, match="DQLLearner.alpah: unknown setting"):
        DQLLearner(env=AuctionEnv(tiny_system), rng=rng, alpah=0.5)


# ------------------------------------------------------------------ fuzz
FAST_LEARNERS = ["greedy", "random", "high_only", "subg_reserve", "subg_cql", "cql", "dql"]
NEURAL_LEARNERS = ["iql", "qmix", "subg_dqn", "vdn"]


def base_configs(compose_cfg, learners: list[str]) -> dict[str, dict]:
    """The composed config of each learner (plain dicts), small budgets."""
    overrides = ["system=system1", "debug=smoke", "env.horizon=6"]
    return {
        name: OmegaConf.to_container(compose_cfg([f"learner={name}", *overrides]))
        for name in learners
    }


junk = st.one_of(
    st.integers(-3, 40),
    st.sampled_from([-(2**63), 2**63, 10**12, 0, 1, -1]),
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from(["", "abc", "1e3", "soft", "hard", "l2", "spread", "true", "cpu", "T1", "R1"]),
    st.booleans(),
    st.none(),
    st.lists(st.integers(-2, 20), max_size=3),
    st.dictionaries(st.sampled_from(["_target_", "a", "T1"]), st.integers(0, 3), max_size=2),
)
labels = st.one_of(
    st.sampled_from(["T1", "T2", "T3", "T10", "pick", "R1", "R2", "arm", "", " "]),
    st.integers(-1, 3),
    st.floats(width=16),
    st.none(),
    st.booleans(),
)
keys = st.one_of(  # as labels, without null: a config key cannot be null (OmegaConf)
    st.sampled_from(["T1", "T2", "T3", "T10", "pick", "R1", "R2", "arm", "", " "]),
    st.integers(-1, 3),
    st.floats(width=16),
    st.booleans(),
)
robot_spec = st.one_of(
    st.lists(labels, max_size=3),
    st.dictionaries(keys, junk, max_size=3),
    junk,
)
system_file = st.one_of(
    st.fixed_dictionaries(
        {"name": st.just("fuzz"), "robots": st.dictionaries(keys, robot_spec, max_size=4)},
        optional={
            "task_types": st.one_of(
                junk,
                st.dictionaries(
                    keys,
                    st.one_of(
                        junk,
                        st.dictionaries(
                            st.sampled_from(["duration_low", "duration_high", "x"]),
                            junk,
                            max_size=2,
                        ),
                    ),
                    max_size=2,
                ),
            ),
            "env": st.one_of(junk, st.dictionaries(st.sampled_from(["horizon", "slots"]), junk)),
            "extra": junk,
        },
    ),
    st.fixed_dictionaries(
        {"name": st.just("fuzz"), "n_robots": junk},
        optional={"n_task_types": junk, "density": junk, "seed": junk},
    ),
    junk,
)


@st.composite
def malformed_config(draw, bases: dict[str, dict]) -> tuple[dict, str]:
    """A config of ``bases`` with one part broken: (config, the key or culprit to name)."""
    learner = draw(st.sampled_from(list(bases)))
    cfg = copy.deepcopy(bases[learner])
    where = draw(st.sampled_from(["learner", "env", "run", "system", "unknown"]))
    if where == "system":
        cfg["system"] = draw(system_file)
        return cfg, "system"
    if where == "unknown":
        section = draw(st.sampled_from(["learner", "env", "train", "eval", "limits"]))
        key = draw(st.sampled_from(["alpah", "horizonn", "episodez", "x"]))
        cfg[section][key] = draw(junk)
        return cfg, f"{section}.{key}"
    if where == "learner":
        keys = [k for k in cfg["learner"] if not k.startswith("_")] or ["_partial_"]
        key, section = draw(st.sampled_from(keys)), "learner"
    elif where == "env":
        section, key = "env", draw(st.sampled_from(sorted(cfg["env"])))
    else:
        section = draw(st.sampled_from(["train", "eval", "limits", "seed"]))
        key = None if section == "seed" else draw(st.sampled_from(sorted(cfg[section])))
    value = draw(junk)
    if key is None:
        cfg["seed"] = value
        return cfg, "seed"
    cfg[section][key] = value
    return cfg, f"{section}.{key}"


def smoke_or_refusal(cfg: dict, culprit: str) -> str:
    """Validate; when accepted, build the run and play a few ticks. Returns what happened."""
    config = OmegaConf.create(cfg)
    try:  # validate_config checks what relates settings (eps_end <= eps_start) first
        run = build_run(config)
    except ConfigError as err:
        message = str(err)
        leaf = culprit.rsplit(".", 1)[-1]
        named = culprit in message or leaf in message or culprit.split(".")[0] in message
        assert named, f"{message!r} does not name {culprit!r}"
        assert "Traceback" not in message
        return "refused"
    env, learner = run.env, run.learner
    view = learner.encode(env)
    for _ in range(4):
        actions = learner.act(view, env.action_mask, explore=True)
        assert np.take_along_axis(env.action_mask, actions[..., None], axis=2).all()
        result = env.step(actions)
        after = learner.encode(env)
        learner.update(view, actions, result, after, env.action_mask)
        view = after
    assert math.isfinite(float(np.asarray(result.team_reward).sum()))
    return "accepted"


FUZZ = settings(
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def test_fuzz_malformed_configs_are_refused_by_name_or_run(compose_cfg):
    """Every malformed config is refused by name or runs; the fuzz saw both outcomes."""
    outcomes = {"accepted": 0, "refused": 0}

    @settings(FUZZ, max_examples=220)
    @given(case=malformed_config(base_configs(compose_cfg, FAST_LEARNERS)))
    def one_case(case):
        outcomes[smoke_or_refusal(*case)] += 1

    one_case()
    # not vacuous: hypothesis replays failing examples too, so count at least what must happen
    assert outcomes["accepted"] >= 10 and outcomes["refused"] >= 100, outcomes


@pytest.mark.slow
def test_fuzz_neural_learners(compose_cfg):
    @settings(FUZZ, max_examples=80)
    @given(case=malformed_config(base_configs(compose_cfg, NEURAL_LEARNERS)))
    def one_case(case):
        smoke_or_refusal(*case)

    one_case()


def test_declared_types_cover_the_supported_annotations():
    assert is_checked(typing.Annotated[int | None, "x"])
    assert not is_checked(np.ndarray)
