"""expert_iteration: the planner's labels, a student that learns its teacher, refused inputs."""

from __future__ import annotations

import copy
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.fixed import TeamReserveLearner
from mrta_rl.learners.neural.expert_iteration import (
    ExpertIterationLearner,
    match_bids,
    planner_labels,
)
from mrta_rl.learners.planning.rollout import CANDIDATES, RolloutPlanner
from mrta_rl.runners import train
from tests.conftest import ROOT, paper_system

SMALL = {"embed_dim": 8, "heads": 2, "samples": 2, "horizon": 4}
PLANNER = ("samples", "horizon", "candidates", "base", "gamma", "margin", "neighbours")


def make(batch=4, seed=0, **hp):
    env = AuctionEnv(
        paper_system("system1"), AuctionParams(horizon=30), batch_size=batch, seed=seed
    )
    return ExpertIterationLearner(env=env, rng=np.random.default_rng(seed), **(SMALL | hp)), env


# ---------------------------------------------------------------------------------- labels
def test_soft_labels_by_hand():
    """Per robot: the softmax of the candidates' returns over the actions they give it.

    Copy 0: returns ln 3 and 0 at scale 1 weigh the two candidates 3/4 and 1/4. Robot 0 bids
    for slot 1 in the first and waits in the second: soft [1/4, 3/4, 0]; with weight 1/2
    beside the chosen bid (slot 1): [1/8, 7/8, 0]. Robot 1 bids for slot 2 in both: one-hot.
    The third candidate repeats the first (not rolled out: -inf) and counts once. Copy 1 had
    no choice (every return -inf): its label is the chosen action alone.
    """
    chosen = np.array([[1, 2], [0, 1]])
    candidates = np.array([[[1, 2], [0, 1]], [[0, 2], [0, 1]], [[1, 2], [0, 1]]])  # [C, B, m]
    returns = np.array([[np.log(3), -np.inf], [0.0, -np.inf], [-np.inf, -np.inf]])  # [C, B]
    labels = planner_labels(chosen, candidates, returns, scale=1.0, weight=0.5, n_actions=3)
    np.testing.assert_allclose(labels[0, 0], [1 / 8, 7 / 8, 0], rtol=1e-6)
    np.testing.assert_allclose(labels[0, 1], [0, 0, 1])
    np.testing.assert_allclose(labels[1], [[1, 0, 0], [0, 1, 0]])
    hard = planner_labels(chosen, candidates, returns, scale=1.0, weight=0.0, n_actions=3)
    np.testing.assert_array_equal(hard.argmax(-1), chosen)
    assert hard.sum() == chosen.size


def test_matched_bids_by_hand():
    """Bids by decreasing margin over waiting, one per slot and robot.

    Robot 0's margins for slots 1, 2: 5, 4; robot 1's: 6, -1; robot 2's: 3, 2, but it may not
    bid for slot 1. Argmax sends robots 0 and 1 to slot 1 (one bids in vain). Matched: robot
    1 takes slot 1 (margin 6), robot 0 its next best, slot 2 (4); robot 2 is left only slot 2,
    taken, so it waits. A copy whose bids all score below waiting waits.
    """
    logits = torch.tensor(
        [
            [[0.0, 5.0, 4.0], [1.0, 7.0, 0.0], [0.0, 3.0, 2.0]],
            [[2.0, 1.0, 0.0], [0.0, -1.0, -2.0], [0.5, 0.0, 0.4]],
        ]
    )
    mask = torch.ones(2, 3, 3, dtype=torch.bool)
    mask[0, 2, 1] = False
    assert logits.argmax(-1)[0].tolist() == [1, 1, 1]  # robot 2's best is masked, too
    assert match_bids(logits, mask).tolist() == [[2, 1, 0], [0, 0, 0]]
    batched = match_bids(logits[None].expand(4, 2, 3, 3), mask[None].expand(4, 2, 3, 3))
    assert batched.shape == (4, 2, 3) and (batched == match_bids(logits, mask)).all()


def rounds_of_best_bids(logits: torch.Tensor, mask: torch.Tensor) -> list[list[int]]:
    """The matching as the docstring tells it, one round per bid: per copy, the best remaining
    (robot, slot) margin (equal margins: the first robot, then the first slot) while positive."""
    out = []
    for scores, valid in zip(logits.tolist(), mask.tolist(), strict=True):
        actions = [0] * len(scores)
        pairs = {
            (r, k): row[k + 1] - row[0]
            for r, row in enumerate(scores)
            for k in range(len(row) - 1)
            if valid[r][k + 1]
        }
        while pairs:
            (robot, slot), best = max(pairs.items(), key=lambda p: (p[1], -p[0][0], -p[0][1]))
            if best <= 0:
                break
            actions[robot] = slot + 1
            pairs = {(r, k): v for (r, k), v in pairs.items() if r != robot and k != slot}
        out.append(actions)
    return out


@pytest.mark.parametrize(("m", "K"), [(1, 1), (3, 5), (6, 2), (7, 7)])
def test_matched_bids_take_the_best_margin_first_on_random_scores_with_ties(m, K):
    """Scores on a coarse grid (many equal margins), a random mask: as the rounds of best bids."""
    generator = torch.Generator().manual_seed(m * 100 + K)
    logits = torch.randint(-3, 4, (64, m, K + 1), generator=generator).float() / 2
    mask = torch.rand(64, m, K + 1, generator=generator) < 0.7
    mask[..., 0] = True
    assert match_bids(logits, mask).tolist() == rounds_of_best_bids(logits, mask)


def test_the_labels_are_the_teachers_actions_on_the_states_given():
    """On states reached by the greedy rule, the labels are the planner's own decisions.

    The same planner, built apart with the same settings and generator state, decides the
    same joint actions; every label is a distribution, and a robot with no valid bid (busy or
    nothing to bid for) is labelled "wait".
    """
    learner, env = make(batch=6, soft_targets=0.3, neighbours=["drop", "add"])
    env.reset()
    rule = TeamReserveLearner(
        env=env,
        rng=np.random.default_rng(1),
        grouping="team",
        order="fewest_types",
        **CANDIDATES["hold"],
    )
    planner = RolloutPlanner(
        env=env,
        rng=copy.deepcopy(learner.rng),
        **{key: learner.hp[key] for key in PLANNER},
    )
    checked = 0
    for _ in range(12):
        chosen, labels = learner.teach()
        expected = planner.act(planner.encode(env), env.action_mask, explore=False)
        np.testing.assert_array_equal(chosen, expected)
        np.testing.assert_allclose(labels.sum(-1), 1.0, rtol=1e-6)
        assert (labels[~env.action_mask] == 0).all()  # no weight on an invalid action
        idle = ~env.action_mask[..., 1:].any(-1)
        assert (labels[idle][:, 0] == 1).all()
        checked += int((~idle).sum())
        env.step(rule.act(rule.encode(env), env.action_mask, explore=False))
    assert checked > 0  # some robots had a choice
    assert learner.labelled == 12 * 6


@pytest.mark.parametrize("decode", ["argmax", "match"])
def test_an_untrained_student_on_the_base_prior_plays_its_base(decode):
    """prior=base: the bonus goes to the base's action, so the untrained student is the base."""
    learner, env = make(batch=5, prior="base", base="hold", decode=decode)
    env.reset()
    base = TeamReserveLearner(
        env=env,
        rng=np.random.default_rng(0),
        grouping="team",
        order="fewest_types",
        **CANDIDATES["hold"],
    )
    bids = 0
    while not env.done.any():
        expected = base.act(base.encode(env), env.action_mask, explore=False)
        played = learner.act(learner.encode(env), env.action_mask, explore=False)
        np.testing.assert_array_equal(played, expected)
        bids += int((expected > 0).sum())
        env.step(played)
    assert bids > 0


def test_outside_collection_the_student_plays_and_labels_itself():
    """Evaluation and the replay probe play the student; the teacher is never asked."""
    learner, env = make(batch=3)
    env.reset()
    view = learner.encode(env)
    actions = learner.act(view, env.action_mask, explore=False)
    assert learner.labelled == 0
    td = learner.collection_policy(view.clone())
    np.testing.assert_array_equal(td.get(("agents", "action")).numpy(), actions)
    np.testing.assert_array_equal(td.get(("agents", "target")).argmax(-1).numpy(), actions)
    assert learner.labelled == 0


# ---------------------------------------------------------------------------------- learning
def test_a_student_fitted_to_a_fixed_teacher_reproduces_it(compose_cfg, tmp_path):
    """The teacher is the hold rule alone (one candidate): the trained student plays the rule.

    Trained through the runner on System-I's smoke horizon with the teacher always playing;
    evaluated on states of other task streams, reached by the rule: the student's bids agree
    with the rule's on at least 95 % of the robots that have a choice (the untrained student
    plays greedy, which agrees on far fewer).
    """
    args = [
        "learner=expert_iteration",
        "system=system1",
        "debug=smoke",
        "train.episodes=8",
        "train.batch_size=8",
        "learner.candidates=[hold]",
        "learner.neighbours=[]",
        "learner.base=hold",
        "learner.prior=greedy",  # the untrained student plays greedy, not the rule
        "learner.beta_start=1.0",
        "learner.beta_end=1.0",
        "train.validate_every=0",
        "train.keep_best=false",
        "learner.warmup_frames=100",
        "learner.updates_per_collect=10",
        "learner.lr=0.003",
    ]
    train(compose_cfg(args), run_dir=tmp_path)
    env = AuctionEnv(paper_system("system1"), AuctionParams(horizon=100), batch_size=8, seed=77)
    saved = json.loads((tmp_path / "learner" / "learner.json").read_text())["hyperparameters"]
    student = ExpertIterationLearner(env=env, rng=np.random.default_rng(0), **saved)
    student.load(tmp_path / "learner")
    env.reset()
    rule = TeamReserveLearner(
        env=env,
        rng=np.random.default_rng(0),
        grouping="team",
        order="fewest_types",
        **CANDIDATES["hold"],
    )
    untrained, _ = make(batch=8, prior="greedy")
    agree = untrained_agree = deciding = 0
    while not env.done.any():
        ours = rule.act(rule.encode(env), env.action_mask, explore=False)
        theirs = student.act(student.encode(env), env.action_mask, explore=False)
        start = untrained.act(untrained.encode(env), env.action_mask, explore=False)
        choice = env.action_mask[..., 1:].any(-1)
        agree += int(((ours == theirs) & choice).sum())
        untrained_agree += int(((ours == start) & choice).sum())
        deciding += int(choice.sum())
        env.step(ours)
    assert agree >= 0.95 * deciding, (agree, deciding)
    assert untrained_agree < 0.9 * deciding, (untrained_agree, deciding)


# ---------------------------------------------------------------------------------- refused
def script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "train.py"), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )


@pytest.fixture(scope="module")
def system2_run(tmp_path_factory):
    """A trained run of another team (System-II) whose table is that team's: a teacher's base
    System-I cannot use (a policy that fits any team plays System-I, as with ``init=``)."""
    run_dir = tmp_path_factory.mktemp("system2") / "run"
    done = script(
        "learner=cql",
        "system=system2",
        "debug=smoke",
        "train.episodes=1",
        f"hydra.run.dir={run_dir}",
    )
    assert done.returncode == 0, done.stderr
    return run_dir


def test_a_teacher_of_another_team_is_refused_in_one_line(system2_run, tmp_path):
    run_dir = tmp_path / "run"
    done = script(
        "learner=expert_iteration",
        "system=system1",
        "debug=smoke",
        f"learner.base={system2_run}",
        f"hydra.run.dir={run_dir}",
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert "another team (system2, not system1)" in lines[0]
    assert "Traceback" not in done.stderr
    assert not run_dir.exists()


@pytest.mark.parametrize(
    ("setting", "culprit"),
    [
        ("learner.max_task_types=3", "learner.max_task_types"),  # System-I has 8 task types
        ("learner.embed_dim=10", "learner.embed_dim"),  # not a multiple of the 4 heads
        ("learner.buffer_size=2000000000", "learner.buffer_size"),  # past the memory limit
        ("learner.beta_end=0.5", "learner.beta_end"),  # above beta_start=0.2
        ("learner.base=hld", "learner.base"),  # a misspelt rule
    ],
)
def test_bad_input_is_refused_in_one_line_before_any_work(tmp_path, setting, culprit):
    run_dir = tmp_path / "run"
    done = script(
        "learner=expert_iteration",
        "system=system1",
        "debug=smoke",
        "learner.beta_start=0.2",
        setting,
        f"hydra.run.dir={run_dir}",
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and culprit in lines[0], lines
    assert not run_dir.exists()
