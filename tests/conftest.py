"""Shared fixtures: a seeded generator, a tiny system and params, and Hydra config composition."""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.systems import RobotSystem, build_system

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
# The Ctrl-C tests send SIGINT to a script as a terminal would to a foreground process. A suite
# started in the background (`pytest &`, nohup, some CI runners) inherits SIGINT *ignored*, and so
# would every script it starts: Python then never raises KeyboardInterrupt and those tests hang.
# A Python-level handler is reset to the default at exec, so the scripts get a normal Ctrl-C.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def paper_system(name: str) -> RobotSystem:
    """System-I or System-II (paper Tables 1-2) from ``conf/system/<name>.yaml``."""
    return build_system(yaml.safe_load((CONF / "system" / f"{name}.yaml").read_text()))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def tiny_system() -> RobotSystem:
    """Two robots, two task types: R1 does T1 and T2, R2 does T2 only."""
    return build_system({"name": "tiny", "robots": {"R1": ["T1", "T2"], "R2": ["T2"]}})


@pytest.fixture
def tiny_params() -> AuctionParams:
    return AuctionParams(horizon=20)


def compose_config(overrides: list[str], config_name: str = "config") -> DictConfig:
    """Compose ``conf/<config_name>.yaml`` with overrides, as ``@hydra.main`` would.

    Without a ``learner=`` override the train config uses ``learner=greedy``, so tests do not
    depend on any particular trained learner. The Hydra node is kept and registered, so that
    ``HydraConfig.get().runtime.choices`` works as in a real run; the caller passes ``run_dir``.
    """
    overrides = list(overrides)
    keys = {o.split("=")[0].lstrip("+~") for o in overrides}
    if config_name == "config" and "learner" not in keys:
        overrides.insert(0, "learner=greedy")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose(config_name=config_name, overrides=overrides, return_hydra_config=True)
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]  # as in a real run: cfg holds the job config, HydraConfig the rest
    return cfg


@pytest.fixture(scope="session")
def compiled_env() -> None:
    """The env kernels a run steps with (``envs/kernel.py``), compiled here if not cached.

    numba writes what it compiles to its cache (``cache=True``), so scripts a test starts load
    the kernels instead of compiling them; on an empty cache, concurrent workers (joblib) would
    otherwise each compile the same kernels at the same time.
    """
    env = AuctionEnv(paper_system("system1"), AuctionParams(horizon=4), batch_size=2)
    env.step(env.fixed_actions("greedy"))


@pytest.fixture
def compose_cfg() -> Iterator[Callable[..., DictConfig]]:
    """``compose_cfg(["system=system1", ...], config_name="config")`` -> composed config."""
    yield compose_config
    GlobalHydra.instance().clear()
    HydraConfig.instance().cfg = None  # forget this run's choices
