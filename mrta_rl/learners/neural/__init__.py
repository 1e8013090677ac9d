"""Torch learners built from TorchRL parts: subG-DQN, VDN, QMIX, IQL, MAPPO and IPPO."""

from __future__ import annotations

from mrta_rl.learners.neural.ippo import IPPOLearner
from mrta_rl.learners.neural.iql import IQLLearner
from mrta_rl.learners.neural.mappo import MAPPOLearner
from mrta_rl.learners.neural.qmix import QMIXLearner
from mrta_rl.learners.neural.subg_dqn import SubGDQNLearner
from mrta_rl.learners.neural.torch_learner import TorchLearner
from mrta_rl.learners.neural.vdn import VDNLearner

__all__ = [
    "IPPOLearner",
    "IQLLearner",
    "MAPPOLearner",
    "QMIXLearner",
    "SubGDQNLearner",
    "TorchLearner",
    "VDNLearner",
]
