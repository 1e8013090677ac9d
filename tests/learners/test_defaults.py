"""Each learner default has one home, its ``conf/learner`` yaml: no class states another value.

For every learner the registry lists (the shipped ones, and a user config dir's yaml that
extends one of them), no keyword default of the class's ``__init__`` along its bases differs from
the value its yaml composes; a learner built in Python with no settings holds the settings a
``learner=<name>`` run is built with.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from omegaconf import OmegaConf

from mrta_rl.conf_paths import learner_block, learner_settings
from mrta_rl.config import check_keywords
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.registry import learner_files, learner_named
from mrta_rl.partition import subg_partition
from tests.conftest import paper_system

LEARNERS = list(learner_files())


def signature_defaults(cls: type) -> dict:
    """Every keyword default of ``__init__`` along the class's bases (the subclass's first)."""
    defaults: dict = {}
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or init is object.__init__:
            continue
        for p in inspect.signature(init).parameters.values():
            if p.default is not inspect.Parameter.empty:
                defaults.setdefault(p.name, p.default)
    return defaults


def disagreements(cls: type, settings: dict) -> list[str]:
    """The settings of a yaml whose class default is another value."""
    defaults = signature_defaults(cls)
    return [
        f"{key}: class {defaults[key]!r}, yaml {value!r}"
        for key, value in settings.items()
        if key in defaults and defaults[key] != value and list(defaults[key] or ()) != value
    ]


@pytest.fixture
def user_dir(tmp_path):
    """A user config dir whose ``learner/qmix_set.yaml`` extends the shipped ``qmix``."""
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "qmix_set.yaml").write_text(
        "defaults:\n  - qmix\n  - _self_\nnetwork: set\n"
    )
    return tmp_path


@pytest.mark.parametrize("name", [*LEARNERS, "qmix_set"])
def test_no_class_default_differs_from_its_yaml(name, user_dir):
    files = learner_files([user_dir])
    assert name in files
    cls = learner_named(name, [user_dir])
    settings = learner_settings(learner_block(name, files))
    if name == "qmix_set":  # qmix's settings under its own
        assert settings == {**learner_settings(learner_block("qmix", files)), "network": "set"}
    assert disagreements(cls, settings) == []


@pytest.mark.parametrize("name", LEARNERS)
def test_a_learner_built_in_python_has_the_settings_of_its_run(compose_cfg, name):
    """``Learner(env=..., rng=...)`` holds the settings ``learner=<name>`` builds it with."""
    cls = learner_named(name)
    block = OmegaConf.to_container(compose_cfg([f"learner={name}"]).learner)
    run = check_keywords(cls, {k: v for k, v in block.items() if not k.startswith("_")}, name)
    assert cls.complete_settings({}) == run
    system = paper_system("system1")
    partition = subg_partition(system) if cls.requires_partition else None
    active = partition.active_tasks(system) if partition is not None else None
    # a batch of whole ticks of every copy (reserve_es: of 2 x pairs policies)
    env = AuctionEnv(system, AuctionParams(horizon=20), batch_size=24, active_tasks=active)
    learner = cls(env=env, rng=np.random.default_rng(0), partition=partition)
    assert learner.hp == run
