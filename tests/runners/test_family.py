"""Training on a family of teams (system.family), and a learned state played on any team (init=)."""

from __future__ import annotations

import collections
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import example, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from mrta_rl.config import ConfigError
from mrta_rl.runners import train
from mrta_rl.runners.validation import validate_config
from mrta_rl.systems import MAX_PAIRS, SystemConfigError, build_system, system_shape
from mrta_rl.systems.family import EVAL_TEAM, build_family
from tests.runners.test_checkpoint import (
    assert_same_run,
    killed_at_checkpoint,
    resumed_run,
    save_hydra_files,
    script,
)

ROOT = Path(__file__).resolve().parents[2]
FAMILY = yaml.safe_load((ROOT / "conf" / "system" / "family.yaml").read_text())
SMOKE = ["learner=net_es", "system=family", "debug=smoke"]


def saved_theta(run_dir: Path) -> np.ndarray:
    with np.load(run_dir / "learner" / "net_es.npz") as saved:
        return saved["theta"]


def test_teams_are_drawn_in_the_ranges_the_same_every_time():
    family = build_family(FAMILY)
    ranges = FAMILY["family"]
    teams = [family.team(k) for k in range(30)]
    for k, team in enumerate(teams):
        assert team.name == f"family[{k}]"
        assert ranges["n_robots"][0] <= team.n_robots <= ranges["n_robots"][1]
        assert ranges["n_task_types"][0] <= team.n_task_types <= ranges["n_task_types"][1]
        # the scaled auction: 3 slots per 10 robots, rounded up (System-II: 3)
        assert team.env_overrides["slots"] == -(-3 * team.n_robots // 10)
        assert np.array_equal(team.willingness, family.team(k).willingness)
    assert len({t.n_robots for t in teams}) > 5  # the teams differ
    # the run plays team 0; the config's shape is the largest team, for the memory check
    assert build_system(FAMILY).name == f"family[{EVAL_TEAM}]"
    assert system_shape(FAMILY) == (ranges["n_robots"][1], ranges["n_task_types"][1])


def test_willingness_is_drawn_per_pair_in_its_range():
    family = build_family({**FAMILY, "family": {**FAMILY["family"], "willingness": [0.5, 0.8]}})
    d = family.team(3).willingness
    assert ((d == 0) | ((d >= 0.5) & (d <= 0.8))).all() and (d > 0).any()
    assert len(np.unique(d[d > 0])) > 1


@pytest.mark.parametrize(
    ("family", "match"),
    [
        ({"n_robots": [10, 5], "n_task_types": [3, 4], "density": [0.2, 0.3]}, "family.n_robots"),
        ({"n_robots": [5, 10], "n_task_types": [3, 4], "density": [0.2, 1.5]}, "family.density"),
        ({"n_robots": [5.5, 10], "n_task_types": [3, 4], "density": [0.2, 0.3]}, "integers"),
        ({"n_robots": [5, 10], "n_task_types": [3, 4]}, "lacks \\['density'\\]"),
        (
            {"n_robots": [5, 10], "n_task_types": [3, 4], "density": [0.2, 0.3], "size": [1, 2]},
            "unknown keys \\['size'\\]",
        ),
        (
            {
                "n_robots": [5, 10],
                "n_task_types": [3, 4],
                "density": [0.2, 0.3],
                "willingness": [0, 1],
            },
            "family.willingness",
        ),
    ],
)
def test_bad_ranges_are_refused_naming_the_key(family, match):
    with pytest.raises(SystemConfigError, match=match):
        build_family({"name": "family", "family": family})


def test_a_family_run_trains_on_its_teams_and_is_evaluated_on_team_0(compose_cfg, tmp_path):
    metrics = train(compose_cfg([*SMOKE, "train.episodes=3"]), run_dir=tmp_path)
    family = build_family(FAMILY)
    trained_on = json.loads((tmp_path / "learner" / "team.json").read_text())
    assert trained_on["robots"] == list(family.team(3).robots)  # the last episode's team
    assert metrics["system"] == "family" and metrics["train"]["episodes"] == 3
    evaluated = family.team(EVAL_TEAM)
    assert set(metrics["eval"]["ctr"]) == set(evaluated.task_types)


def test_init_plays_a_family_policy_on_another_team(compose_cfg, tmp_path):
    """Zero-shot: the family run's weights, unchanged, on System-I, against greedy as usual."""
    family = compose_cfg([*SMOKE, "train.episodes=3"])
    save_hydra_files(family, tmp_path / "family", "net_es", "family")  # a run dir, as Hydra's
    train(family, run_dir=tmp_path / "family")
    zero = train(
        compose_cfg(
            [
                "learner=net_es",
                "system=system1",
                "debug=smoke",
                "train.episodes=0",
                f"init={tmp_path / 'family'}",
            ]
        ),
        run_dir=tmp_path / "zero",
    )
    assert np.array_equal(saved_theta(tmp_path / "zero"), saved_theta(tmp_path / "family"))
    assert zero["system"] == "system1" and "baseline_greedy" in zero
    train(
        compose_cfg(["learner=net_es", "system=system1", "debug=smoke", "train.episodes=0"]),
        run_dir=tmp_path / "untrained",
    )
    assert not np.array_equal(saved_theta(tmp_path / "untrained"), saved_theta(tmp_path / "zero"))


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["learner=qmix", "system=family"], "qmix .* tied to one team.*net_es"),
        (["learner=qmix", "init=somewhere"], "init: learner qmix .* tied to one team"),
        (["learner=net_es", "init=/nonexistent/run"], "init: /nonexistent/run"),
    ],
)
def test_learners_tied_to_one_team_are_refused_before_any_work(
    compose_cfg, tmp_path, overrides, match
):
    with pytest.raises(ConfigError, match=match):
        train(compose_cfg([*overrides, "debug=smoke"]), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_init_refuses_a_run_of_another_learner(compose_cfg, tmp_path):
    family = compose_cfg([*SMOKE, "train.episodes=1"])
    save_hydra_files(family, tmp_path / "family", "net_es", "family")
    train(family, run_dir=tmp_path / "family")
    with pytest.raises(ConfigError, match="trained NetESLearner, not ReserveESLearner"):
        train(
            compose_cfg(["learner=reserve_es", "debug=smoke", f"init={tmp_path / 'family'}"]),
            run_dir=tmp_path / "run",
        )
    assert not (tmp_path / "run").exists()


def test_a_family_run_killed_and_resumed_ends_like_an_uninterrupted_run(compose_cfg, tmp_path):
    args = [*SMOKE, "train.episodes=40", "train.checkpoint_every=5"]
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    killed_after = killed_at_checkpoint(args, cut_dir, 15)
    resumed = script("scripts/train.py", f"resume={cut_dir}")
    train(compose_cfg(args), run_dir=full_dir)
    assert killed_after <= resumed_run(resumed, cut_dir) < 40
    assert_same_run(full_dir, cut_dir)


# ---------------------------------------------------------------------------------- the fuzz
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-3, 40),
    st.sampled_from([2**63, 10**30, -(2**63)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["", "4", "abc", "1e3", "nan"]),
)
JUNK = st.one_of(
    SCALARS,
    st.lists(SCALARS, max_size=4),
    st.dictionaries(st.sampled_from(["lo", "hi", "n_robots"]), SCALARS, max_size=2),
)


@st.composite
def sizes(draw, low: int = 1, high: int = 40) -> list[int]:
    lo = draw(st.integers(low, high))
    return [lo, draw(st.integers(lo, high))]


@st.composite
def fractions(draw, low: float, exclude_low: bool = False) -> list[float]:
    ends = st.floats(low, 1.0, exclude_min=exclude_low) | st.sampled_from([low or 1.0, 1.0, 1])
    return sorted([draw(ends), draw(ends)])


VALID = {
    "n_robots": sizes(),
    "n_task_types": sizes(high=30),
    "density": fractions(0.0),
    "willingness": fractions(0.0, exclude_low=True),
}


@st.composite
def broken_range(draw, key: str) -> list:
    """A ``[lo, hi]`` of ``key`` broken one way, or any value at all."""
    lo, hi = draw(VALID[key])
    how = draw(
        st.sampled_from(["reversed", "nan", "inf", "float", "huge", "negative", "three", "junk"])
    )
    if how == "reversed":
        return [hi + 1, lo]
    if how in ("nan", "inf"):
        value = math.nan if how == "nan" else draw(st.sampled_from([math.inf, -math.inf]))
        return draw(st.sampled_from([[lo, value], [value, hi]]))
    if how == "float":
        return [float(lo), float(hi) + 0.5]
    if how == "huge":
        return [lo, draw(st.sampled_from([10**9, 2**63, 10**30, 1e308]))]
    if how == "negative":
        return [-abs(hi) - 1, hi]
    if how == "three":
        return [lo, hi, hi]
    return draw(JUNK)


@st.composite
def family_case(draw) -> tuple[dict, tuple[str, ...]]:
    """A family system config, valid or broken in one place: (config, names a refusal may use)."""
    system = {**FAMILY, "family": {key: draw(VALID[key]) for key in VALID}}
    where = draw(
        st.sampled_from(
            ["valid", *VALID, "missing", "extra", "family", "seed", "scale_auction", "env", "name"]
        )
    )
    ranges = system["family"]
    if where in VALID:
        ranges[where] = draw(broken_range(where))
        return system, (f"family.{where}",)
    if where == "missing":
        key = draw(st.sampled_from(list(VALID)))
        del ranges[key]
        return system, (key,)  # willingness is optional: then accepted
    if where == "extra":
        key = draw(st.sampled_from(["size", "n_robot", "seed", "1"]))
        ranges[key] = draw(JUNK)
        return system, (key,)
    if where == "family":
        system["family"] = draw(JUNK)
        return system, ("family",)
    if where == "env":
        system["env"] = draw(
            JUNK | st.fixed_dictionaries({}, optional={"horizon": JUNK, "horizonn": JUNK})
        )
        return system, ("env",)
    if where in ("seed", "scale_auction", "name"):
        system[where] = draw(JUNK)
        return system, (where,)
    return system, ()


def is_number(value, whole: bool = False) -> bool:
    kinds = int if whole else (int, float)
    return isinstance(value, kinds) and not isinstance(value, bool) and math.isfinite(value)


def is_range(value, low: float, high: float, whole: bool = False, open_low: bool = False) -> bool:
    """Whether ``value`` is ``[lo, hi]`` with ``low <= lo <= hi <= high`` (``low < lo``)."""
    if not (isinstance(value, list) and len(value) == 2):
        return False
    lo, hi = value
    if not (is_number(lo, whole) and is_number(hi, whole)):
        return False
    return (lo > low if open_low else lo >= low) and lo <= hi <= high


def is_valid(system: dict) -> bool | None:
    """Whether a family config is valid, as its file format says (None: not decided here)."""
    ranges = system["family"]
    keys = set(ranges) if isinstance(ranges, dict) else set()
    if not set(VALID) - {"willingness"} <= keys <= set(VALID):  # willingness is optional
        return False
    ok = (
        is_range(ranges["n_robots"], 1, math.inf, whole=True)
        and is_range(ranges["n_task_types"], 1, math.inf, whole=True)
        and is_range(ranges["density"], 0, 1)
        and is_range(ranges.get("willingness", [1, 1]), 0, 1, open_low=True)
        and is_number(system.get("seed", 0), whole=True)
        and system.get("seed", 0) >= 0
        and isinstance(system.get("scale_auction", True), bool)
    )
    env = system.get("env")
    if not ok or not (env is None or isinstance(env, dict)):
        return False
    return True if not env else None  # the env block's keys are checked as the run's env.*


def checked_pairs(system: dict) -> int:
    """Robot-task pairs of the largest team of a family config whose sizes are integers."""
    return system["family"]["n_robots"][1] * system["family"]["n_task_types"][1]


def check_team(team, ranges: dict) -> None:
    """A team of a family: sizes and willingness in the ranges, every robot and task type used."""
    assert ranges["n_robots"][0] <= team.n_robots <= ranges["n_robots"][1]
    assert ranges["n_task_types"][0] <= team.n_task_types <= ranges["n_task_types"][1]
    low, high = ranges.get("willingness", (1.0, 1.0))
    pairs = team.willingness[team.willingness > 0]
    assert ((pairs >= low) & (pairs <= high)).all()
    assert (team.willingness > 0).any(axis=1).all() and (team.willingness > 0).any(axis=0).all()


def test_fuzz_family_ranges_are_accepted_in_range_or_refused_naming_the_key(compose_cfg):
    """A ``system.family`` block through the run's validation: accepted when valid, and then its
    teams lie in its ranges, or refused in one short line naming the key; the fuzz saw both
    outcomes. The examples are what the fuzz found: a traceback, a value taken for another, a
    message of 325 characters."""
    base = OmegaConf.to_container(compose_cfg(["learner=net_es", "system=family", "debug=smoke"]))
    outcomes = collections.Counter()

    @settings(max_examples=120, deadline=None, derandomize=True)
    @given(case=family_case())
    @example(case=({**FAMILY, "env": [1, 2]}, ("env",)))  # TypeError from dict()
    @example(case=({**FAMILY, "env": "ab"}, ("env",)))  # ValueError from dict()
    @example(case=({**FAMILY, "scale_auction": "no"}, ("scale_auction",)))  # taken as true
    @example(case=({**FAMILY, "env": {"lo": None}}, ("env",)))  # 325 characters
    def one_case(case):
        system, culprits = case
        try:
            checked = validate_config(OmegaConf.create({**base, "system": system}))
        except ConfigError as err:
            message = str(err)
            assert "\n" not in message and len(message) <= 300, message
            if "robot-task pairs" in message:  # a valid family of teams too big to run
                assert checked_pairs(system) > MAX_PAIRS, message
            else:
                assert is_valid(system) is not True, f"a valid family refused: {message}"
                assert any(name in message for name in culprits), f"{message!r} names no {culprits}"
            outcomes["refused"] += 1
            return
        assert is_valid(system) is not False, "an invalid family accepted"
        assert checked.family is not None
        pairs = checked.family.largest[0] * checked.family.largest[1]
        assert pairs <= MAX_PAIRS, f"a family of teams of {pairs:,} pairs accepted"
        for team in (checked.system, *(checked.family.team(k) for k in (1, 2))):
            check_team(team, system["family"])
        outcomes["accepted"] += 1

    one_case()
    assert outcomes["accepted"] >= 20 and outcomes["refused"] >= 50, outcomes
