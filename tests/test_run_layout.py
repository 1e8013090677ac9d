"""Damaged run-dir files are refused naming the file and the key, never half-used.

``training.json`` through ``resume=``, ``metrics.json`` through the report, ``.hydra/*.yaml``
through ``evaluate_checkpoint`` and ``resume=``: every case is either accepted and ends as the
undamaged run would, or refused with a :class:`~mrta_rl.config.UserError` naming the file and
key, leaving the run dir as it was. Explicit cases first, then a property-based fuzz.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra.core.hydra_config import HydraConfig
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mrta_rl.config import UserError
from mrta_rl.learners.neural.tensor_files import check_state_dict
from mrta_rl.reports import build_report
from mrta_rl.run_layout import read_training_state
from mrta_rl.runners import evaluate_checkpoint, train
from mrta_rl.runners.checkpoint import TrainingCheckpoint
from mrta_rl.runners.torch_loop import COUNTERS as TORCH_COUNTERS
from tests.conftest import compose_config
from tests.runners.test_checkpoint import save_hydra_files, without_timings

OVERRIDES = [
    "learner=subg_cql",
    "system=system1",
    "debug=smoke",
    "train.episodes=4",
    "train.checkpoint_every=1",
    "eval.episodes=1",
    "eval.batch_size=1",
]
STOP_AT = 2


class Killed(BaseException):
    """Stands for SIGKILL right after a checkpoint."""


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> dict[str, Path | dict]:
    """A finished run, and the same run stopped after the checkpoint of episode ``STOP_AT``."""
    root = tmp_path_factory.mktemp("pristine")
    full_dir, cut_dir = root / "full", root / "cut"
    cfg = compose_config(OVERRIDES)
    save_hydra_files(cfg, full_dir, "subg_cql", "system1")
    full = train(cfg, run_dir=full_dir)
    cfg = compose_config(OVERRIDES)
    save_hydra_files(cfg, cut_dir, "subg_cql", "system1")
    save = TrainingCheckpoint.save

    def save_then_die(self, loop, files=None):
        path = save(self, loop, files)
        if loop["episode"] == STOP_AT:
            raise Killed
        return path

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(TrainingCheckpoint, "save", save_then_die)
        with pytest.raises(Killed):
            train(cfg, run_dir=cut_dir)
    HydraConfig.instance().cfg = None
    return {"full": full_dir, "cut": cut_dir, "metrics": full}


def digest(folder: Path) -> str:
    """Hash of every file's path and bytes below ``folder``."""
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(folder)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def state_file(run_dir: Path) -> Path:
    (found,) = run_dir.glob("**/training.json")  # the checkpoint's layout is not fixed here
    return found


def resume(run_dir: Path) -> dict:
    cfg = compose_config([f"resume={run_dir}"])
    HydraConfig.instance().cfg = None  # as from the command line: no overrides but resume=
    try:
        return train(cfg)
    finally:
        HydraConfig.instance().cfg = None


def refused_or_right(run_dir: Path, call, expected: dict | None, *named: str, any_of=()) -> str:
    """``call()`` ends with the undamaged run's metrics, or is refused naming ``named`` (and one
    of ``any_of``)."""
    before = digest(run_dir)
    try:
        result = call()
    except UserError as err:
        message = str(err)
        for culprit in named:
            assert culprit in message, message
        assert not any_of or any(name in message for name in any_of), message
        assert "\n" not in message.strip(), message
        assert digest(run_dir) == before, "a refused call changed the run dir"
        return message
    if expected is not None:
        assert without_timings(result) == without_timings(expected)
    return ""


def damaged_copy(pristine, tmp_path: Path, name: str = "cut") -> Path:
    run_dir = tmp_path / name
    shutil.copytree(pristine[name], run_dir)
    return run_dir


# ---------------------------------------------------------------------------------- training.json
def set_key(state: dict, dotted: str, value) -> None:
    *parents, last = dotted.split(".")
    node = state
    for key in parents:
        node = node[key]
    if value is DELETE:
        del node[last]
    else:
        node[last] = value


DELETE = object()
TRAINING_CASES = {
    "episode missing": ("loop.episode", DELETE, "loop.episode"),
    "episode a string": ("loop.episode", "2", "loop.episode"),
    "episode a float": ("loop.episode", 2.0, "loop.episode"),
    "episode past train.episodes": ("loop.episode", 1_000_000_000, "loop.episode"),
    "episode negative": ("loop.episode", -5, "loop.episode"),
    "env_ticks missing": ("loop.env_ticks", DELETE, "loop.env_ticks"),
    "curve a string": ("loop.curve", "rows", "loop.curve"),
    "curve row a list": ("loop.curve", [[1, 2, 3], [4, 5, 6]], "loop.curve[0]"),
    "curve row without return": ("loop.curve", [{"episode": 1}, {"episode": 2}], "loop.curve[0]"),
    "spent a list": ("loop.spent", [1.0], "loop.spent"),
    "spent negative": ("loop.spent.wall_s", -1.0, "loop.spent.wall_s"),
    "spent a string": ("loop.spent.cpu_s", "12.5", "loop.spent.cpu_s"),
    "spent of an unknown kind": ("loop.spent.gpu_s", 1.0, "loop.spent.gpu_s"),
    "learner state a list": ("learner", [1, 2], "learner"),
    "learner state empty": ("learner", {}, "learner"),
    "learner generator wrong": ("learner.rng", "xyz", "learner"),
}


@pytest.mark.parametrize("case", sorted(TRAINING_CASES))
def test_damaged_training_json_is_refused_naming_file_and_key(case, pristine, tmp_path):
    key, value, named = TRAINING_CASES[case]
    run_dir = damaged_copy(pristine, tmp_path)
    path = state_file(run_dir)
    state = json.loads(path.read_text())
    set_key(state, key, value)
    path.write_text(json.dumps(state))
    message = refused_or_right(run_dir, lambda: resume(run_dir), None, str(path), named)
    assert message, "a damaged training.json was accepted"


def test_truncated_training_json_is_refused(pristine, tmp_path):
    run_dir = damaged_copy(pristine, tmp_path)
    path = state_file(run_dir)
    path.write_text(path.read_text()[:50])
    assert refused_or_right(run_dir, lambda: resume(run_dir), None, str(path), "not valid JSON")


def test_torchrl_loop_training_json_without_frames_is_refused(tmp_path):
    path = tmp_path / "training.json"
    loop = {"episode": 0, "replayed": 0, "curve": []}
    path.write_text(json.dumps({"loop": loop, "learner": {}}))
    with pytest.raises(UserError, match=r"training.json: loop.frames: must be an integer >= 0"):
        read_training_state(path, TORCH_COUNTERS, episodes=4)


def test_undamaged_checkpoint_resumes_to_the_same_end(pristine, tmp_path):
    run_dir = damaged_copy(pristine, tmp_path)
    assert without_timings(resume(run_dir)) == without_timings(pristine["metrics"])


# ---------------------------------------------------------------------------------- the fuzz
JSON_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=False, allow_infinity=False),
    st.text(max_size=5),
    st.lists(st.integers(-3, 3), max_size=3),
    st.dictionaries(
        st.sampled_from(["episode", "env_ticks", "team_return_mean", "x"]),
        st.integers(-2, 5),
        max_size=3,
    ),
)


def paths_of(node, prefix: str = "") -> list[str]:
    """Dotted paths of every node of a JSON or YAML tree (list items as numbers)."""
    out = []
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else []
    )
    for key, value in items:
        path = f"{prefix}.{key}" if prefix else str(key)
        out.append(path)
        if len(out) < 400:
            out += paths_of(value, path)
    return out


def mutate(tree, path: str, how: str, value):
    """A copy of ``tree`` with the node at ``path`` deleted, replaced or made a wrong type."""
    tree = copy.deepcopy(tree)
    *parents, last = path.split(".")
    node = tree
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    key = int(last) if isinstance(node, list) else last
    if how == "delete":
        del node[key]
    else:
        node[key] = value
    return tree


FUZZ = settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def fuzz_case(data, tree, leave_out: str | None = None):
    paths = [p for p in paths_of(tree) if leave_out is None or not p.startswith(leave_out)]
    path = data.draw(st.sampled_from(paths))
    how = data.draw(st.sampled_from(["delete", "replace"]))
    return path, mutate(tree, path, how, data.draw(JSON_VALUES))


@FUZZ
@given(data=st.data())
def test_fuzz_training_json_through_resume(data, pristine, tmp_path_factory):
    run_dir = damaged_copy(pristine, tmp_path_factory.mktemp("fuzz"))
    path = state_file(run_dir)
    key, state = fuzz_case(data, json.loads(path.read_text()))
    path.write_text(json.dumps(state))
    refused_or_right(run_dir, lambda: resume(run_dir), pristine["metrics"], str(path))


@FUZZ
@given(data=st.data())
def test_fuzz_metrics_json_through_the_report(data, pristine, tmp_path_factory):
    run_dir = damaged_copy(pristine, tmp_path_factory.mktemp("fuzz"), "full")
    path = run_dir / "metrics.json"
    key, metrics = fuzz_case(data, json.loads(path.read_text()))
    path.write_text(json.dumps(metrics))
    out = run_dir.parent / "report"
    try:
        refused_or_right(run_dir, lambda: build_report([run_dir], out), None, str(path))
    except Exception as err:  # noqa: BLE001 - the report's other errors name what they can
        raise AssertionError(f"{key}: {err!r}") from err


@FUZZ
@given(data=st.data(), which=st.sampled_from(["evaluate", "resume"]))
def test_fuzz_hydra_config_through_evaluate_and_resume(data, which, pristine, tmp_path_factory):
    name = "full" if which == "evaluate" else "cut"
    run_dir = damaged_copy(pristine, tmp_path_factory.mktemp("fuzz"), name)
    path = run_dir / ".hydra" / "config.yaml"
    # the team is left out: see test_tables_of_another_team_are_refused
    key, config = fuzz_case(data, yaml.safe_load(path.read_text()), leave_out="system.robots.")
    path.write_text(yaml.safe_dump(config))
    call = (
        (lambda: evaluate_checkpoint(run_dir)) if which == "evaluate" else (lambda: resume(run_dir))
    )
    # a changed setting may leave the saved tables unfit for the learner it builds: then the
    # tables' file is the one named
    refused_or_right(
        run_dir, call, None, any_of=(str(path), str(run_dir / "learner"), "checkpoint")
    )


# ---------------------------------------------------------------------------------- tables, weights
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_q_tables_holding_nan_or_inf_are_refused_naming_the_file(value, pristine, tmp_path):
    run_dir = damaged_copy(pristine, tmp_path, "full")
    path = run_dir / "learner" / "q_tables.npz"
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    damaged = [k for k in arrays if k.endswith(".q")]
    for k in damaged:
        arrays[k] = np.full_like(arrays[k], value)
    np.savez(path, **arrays)
    message = refused_or_right(
        run_dir, lambda: evaluate_checkpoint(run_dir), None, str(path), "NaN or infinite"
    )
    assert message and damaged[0] in message


@pytest.mark.parametrize("value", [math.nan, -math.inf])
def test_weights_holding_nan_or_inf_are_refused_naming_the_file(value, tmp_path):
    path = tmp_path / "weights.pt"
    expected = {"layer.weight": torch.zeros(2, 3), "layer.bias": torch.zeros(2)}
    saved = {**expected, "layer.bias": torch.tensor([0.5, value])}
    with pytest.raises(ValueError, match=re.escape(f"{path}: tensor layer.bias holds NaN")):
        check_state_dict(saved, expected, path)
    check_state_dict(expected, expected, path)  # finite weights pass


def test_tables_of_another_team_are_refused(pristine, tmp_path):
    run_dir = damaged_copy(pristine, tmp_path, "full")
    path = run_dir / ".hydra" / "config.yaml"
    config = yaml.safe_load(path.read_text())
    del config["system"]["robots"]["R3"][1]
    path.write_text(yaml.safe_dump(config))
    message = refused_or_right(
        run_dir, lambda: evaluate_checkpoint(run_dir), None, "team.json", "willingness.R3"
    )
    assert message  # refused, not evaluated


def test_alias_bomb_in_the_run_config_is_refused_before_it_is_expanded(pristine, tmp_path):
    run_dir = damaged_copy(pristine, tmp_path, "full")
    path = run_dir / ".hydra" / "config.yaml"
    lines = ['  a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for previous, name in zip("abcdefgh", "bcdefghi", strict=True):
        lines.append(f"  {name}: &{name} [" + ", ".join([f"*{previous}"] * 9) + "]")
    path.write_text(path.read_text() + "laughs:\n" + "\n".join(lines) + "\n")
    message = refused_or_right(
        run_dir, lambda: evaluate_checkpoint(run_dir), None, str(path), "YAML aliases"
    )
    assert message


@pytest.mark.parametrize(
    ("key", "value"),
    [("filename", "../../escaped.csv"), ("log_dir", "/tmp"), ("filename", None)],
)
def test_a_logger_writing_outside_the_run_dir_is_refused(pristine, tmp_path, key, value):
    run_dir = damaged_copy(pristine, tmp_path, "cut")
    path = run_dir / ".hydra" / "config.yaml"
    config = yaml.safe_load(path.read_text())
    config["logger"][key] = value
    path.write_text(yaml.safe_dump(config))
    message = refused_or_right(run_dir, lambda: resume(run_dir), None, f"logger.{key}")
    assert message
    assert not (tmp_path / "escaped.csv").exists()


@pytest.mark.parametrize("damage", ["missing", "garbage"])
def test_a_learner_state_without_its_team_is_refused(pristine, tmp_path, damage):
    run_dir = damaged_copy(pristine, tmp_path, "full")
    team = run_dir / "learner" / "team.json"
    if damage == "missing":
        team.unlink()
    else:
        team.write_text("{not json")
    message = refused_or_right(run_dir, lambda: evaluate_checkpoint(run_dir), None, str(team))
    assert message


@pytest.mark.parametrize("damage", ["alias_bomb", "garbage", "not_yaml"])
def test_a_damaged_hydra_yaml_is_refused_or_loses_only_the_names(pristine, tmp_path, damage):
    """``.hydra/hydra.yaml`` gives only the runs' names: a hostile file is refused before it is
    expanded, a damaged one is evaluated under the class names."""
    run_dir = damaged_copy(pristine, tmp_path, "full")
    path = run_dir / ".hydra" / "hydra.yaml"
    if damage == "alias_bomb":
        lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
        for previous, name in zip("abcdefgh", "bcdefghi", strict=True):
            lines.append(f"{name}: &{name} [" + ", ".join([f"*{previous}"] * 9) + "]")
        path.write_text("\n".join(lines) + "\n")
    elif damage == "garbage":
        path.write_bytes(bytes(range(256)))
    else:
        path.write_text("hydra: [unclosed\n")
    message = refused_or_right(run_dir, lambda: evaluate_checkpoint(run_dir), None, str(path))
    assert bool(message) == (damage != "not_yaml")
