"""Every learner answers for its facts, and a learner class lacking one fails when it is created."""

from __future__ import annotations

import importlib
from typing import ClassVar

import pytest

from mrta_rl.envs import AuctionParams
from mrta_rl.learners import GreedyLearner, Learner
from mrta_rl.learners.base import FACTS, NUMPY_LOOP
from mrta_rl.learners.memory import ResourceEstimate, estimate_resources
from mrta_rl.learners.registry import learner_files, learner_named
from mrta_rl.partition import subg_partition
from tests.conftest import paper_system

LEARNERS = list(learner_files())


@pytest.mark.parametrize("name", LEARNERS)
def test_each_shipped_learner_declares_its_facts(name):
    cls = learner_named(name)
    assert "label" in vars(cls) and cls.label  # its own, not its parent's
    assert cls.kind in ("fixed", "tabular", "neural", "search")
    module, _, function = cls.training_loop.partition(":")
    assert callable(getattr(importlib.import_module(module), function))
    system = paper_system("system1")
    partition = subg_partition(system) if cls.requires_partition else None
    estimate = estimate_resources(cls, system, AuctionParams(), partition, batch_size=4)
    assert isinstance(estimate, ResourceEstimate) and estimate.reason is None
    own = {part: size for part, size in estimate.parts.items() if part != "env copies"}
    # what it keeps besides the env copies: nothing for a fixed policy, tables or networks for
    # the tabular and neural learners (a search learner: its weights, reserve_es's too few to count)
    if cls.kind == "fixed":
        assert sum(own.values()) == 0
    if cls.kind in ("tabular", "neural"):
        assert sum(own.values()) > 0


def test_labels_tell_the_learners_apart():
    labels = [learner_named(name).label for name in LEARNERS]
    assert len(set(labels)) == len(labels)


def test_a_learner_without_a_label_fails_when_created():
    with pytest.raises(TypeError, match=r"UnlabelledGreedy does not declare label"):

        class UnlabelledGreedy(GreedyLearner):
            pass


def test_a_learner_without_its_facts_fails_when_created():
    with pytest.raises(TypeError, match="does not declare " + ", ".join(FACTS)):

        class Bare(Learner):
            label: ClassVar[str] = "bare"

            def act(self, view, mask, *, explore):
                return mask[..., 0] * 0


def test_an_abstract_base_leaves_the_facts_to_its_subclasses():
    class Base(Learner, abstract=True):
        training_loop: ClassVar[str] = NUMPY_LOOP

    with pytest.raises(TypeError, match=r"does not declare kind, estimate_memory"):

        class Child(Base):
            label: ClassVar[str] = "child"


def test_a_neural_learner_without_its_network_count_fails_when_created():
    from mrta_rl.learners.neural.torch_learner import TorchLearner

    with pytest.raises(TypeError, match=r"Uncounted does not declare .*network_weights"):

        class Uncounted(TorchLearner):
            label: ClassVar[str] = "uncounted"
