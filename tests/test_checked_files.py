"""Every file a run reads is checked: damaged, hostile or odd files are refused in one line.

The learner state files of ``net_es`` and ``reserve_es`` (``learner/*.npz``) through ``init=``,
``resume=`` and ``scripts/evaluate.py``; FIFOs, devices, huge and foreign files where a run's
file should be; a team file with a YAML syntax error; a curve.csv cell that is not a number; a
rollout base that is its own base; an update that makes the weights NaN. Each is refused with
one short line naming the file (or the learner and step) and the culprit, never hangs, never
reads without bound, and leaves what was there (a checkpoint) usable. Explicit cases first, then
a property-based fuzz of the ES state files through ``evaluate_checkpoint`` and ``init=``.
"""

from __future__ import annotations

import collections
import hashlib
import json
import math
import os
import random
import resource
import shutil
import signal
import struct
import subprocess
import sys
import warnings
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.core.hydra_config import HydraConfig
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from mrta_rl.commands import use_team_files
from mrta_rl.config import UserError
from mrta_rl.learners.base import NonFiniteState
from mrta_rl.learners.neural.qmix import QMIXLearner
from mrta_rl.learners.search.net_es import NetESLearner
from mrta_rl.learners.search.reserve_es import N_FEATURES, ReserveESLearner
from mrta_rl.reports import build_report
from mrta_rl.reports.collect import read_curve
from mrta_rl.runners import evaluate_checkpoint, train
from mrta_rl.runners.checkpoint import TrainingCheckpoint, latest_checkpoint
from tests.commands.test_cli import assert_user_error, script
from tests.commands.test_cli import train as train_script
from tests.conftest import compose_config
from tests.runners.test_checkpoint import save_hydra_files, without_timings

ROOT = Path(__file__).resolve().parents[1]
ES = ["system=system1", "debug=smoke", "train.batch_size=24", "learner.pairs=2"]
NET_ES = ["learner=net_es", *ES, "train.episodes=2"]
RESERVE_ES = ["learner=reserve_es", *ES, "train.episodes=2"]
MAX_MESSAGE = 300  # characters of a one-line refusal (messages stay short)


def finished_run(run_dir: Path, overrides: list[str], learner: str) -> Path:
    """A run of ``scripts/train.py`` made in this process (its config files as Hydra's)."""
    cfg = compose_config(overrides)
    save_hydra_files(cfg, run_dir, learner, "system1")
    train(cfg, run_dir=run_dir)
    HydraConfig.instance().cfg = None
    return run_dir


@pytest.fixture(scope="module")
def es_runs(tmp_path_factory) -> dict[str, Path]:
    """A finished net_es and a finished reserve_es run on System-I (2 ES steps each)."""
    root = tmp_path_factory.mktemp("es")
    return {
        "net_es": finished_run(root / "net_es", NET_ES, "net_es"),
        "reserve_es": finished_run(root / "reserve_es", RESERVE_ES, "reserve_es"),
    }


def copy_run(es_runs: dict[str, Path], learner: str, tmp_path: Path) -> Path:
    run_dir = tmp_path / f"damaged_{learner}"
    shutil.copytree(es_runs[learner], run_dir)
    return run_dir


def state_path(run_dir: Path, learner: str) -> Path:
    return run_dir / "learner" / f"{learner}.npz"


def rewrite(path: Path, **changes) -> None:
    """The state file with some arrays replaced (as np.savez writes them)."""
    with np.load(path) as saved:
        arrays = {k: saved[k] for k in saved.files}
    arrays.update(changes)
    np.savez(path, **arrays)


def assert_one_line(message: str, *named: str) -> None:
    assert "\n" not in message.strip(), message
    assert len(message) <= MAX_MESSAGE, f"{len(message)} characters: {message}"
    for culprit in named:
        assert culprit in message, message


def refused_by_init(learner: str, source: Path, tmp_path: Path) -> str:
    """``init=<source>`` of a run of the same learner: the refusal's message (no run dir made)."""
    overrides = NET_ES if learner == "net_es" else RESERVE_ES
    run_dir = tmp_path / "init_run"
    with pytest.raises(UserError) as err:
        train(compose_config([*overrides, f"init={source}"]), run_dir=run_dir)
    HydraConfig.instance().cfg = None
    assert not run_dir.exists()
    return str(err.value)


def refused_by_evaluate(run_dir: Path) -> str:
    with pytest.raises(UserError) as err:
        evaluate_checkpoint(run_dir)
    assert not (run_dir / "eval_metrics.json").exists()
    return str(err.value)


# ---------------------------------------------------------------------------------- ES state values
BAD_WEIGHTS = {
    "nan": (np.nan, "NaN or infinite"),
    "inf": (np.inf, "NaN or infinite"),
    "huge": (1e308, "must be within"),
    "complex": (1j, "dtype complex128"),
}


@pytest.mark.parametrize("learner", ["net_es", "reserve_es"])
@pytest.mark.parametrize("case", sorted(BAD_WEIGHTS))
def test_bad_weights_are_refused_by_init_and_evaluate(es_runs, tmp_path, learner, case):
    value, reason = BAD_WEIGHTS[case]
    run_dir = copy_run(es_runs, learner, tmp_path)
    path = state_path(run_dir, learner)
    with np.load(path) as saved:
        theta = saved["theta"].astype(complex if case == "complex" else float)
    theta[3] = value if case != "complex" else theta[3] + value
    rewrite(path, theta=theta)
    assert_one_line(refused_by_init(learner, run_dir, tmp_path), str(path), "theta", reason)
    assert_one_line(refused_by_evaluate(run_dir), str(path), "theta", reason)


STATE_FAULTS = {
    "negative second moment": ("adam_v", lambda a: a - 1.0, "must be >= 0"),
    "negative steps": ("steps", lambda a: np.int64(-5), "must be >= 0"),
    "float steps": ("steps", lambda a: np.float64(2.5), "dtype float64"),
    "first moment of another shape": ("adam_m", lambda a: np.zeros(5), "shape (5,)"),
}


@pytest.mark.parametrize("case", sorted(STATE_FAULTS))
def test_damaged_adam_state_and_step_count_are_refused(es_runs, tmp_path, case):
    key, damage, reason = STATE_FAULTS[case]
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    with np.load(path) as saved:
        rewrite(path, **{key: damage(saved[key])})
    assert_one_line(refused_by_init("net_es", run_dir, tmp_path), str(path), key, reason)
    assert_one_line(refused_by_evaluate(run_dir), str(path), key, reason)


def test_a_negative_second_moment_is_refused_through_the_evaluate_script(es_runs, tmp_path):
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    with np.load(path) as saved:
        rewrite(path, adam_v=saved["adam_v"] - 1.0)
    proc = script("evaluate.py", f"checkpoint={run_dir}")
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, str(path), "adam_v", "must be >= 0")
    assert_one_line(err)
    assert not (run_dir / "eval_metrics.json").exists()


def fake_npz(path: Path, arrays: dict[str, np.ndarray], header: dict[str, tuple]) -> None:
    """An npz whose members named in ``header`` declare that shape but hold a few bytes only."""
    with zipfile.ZipFile(path, "w") as archive:
        for name, array in arrays.items():
            with archive.open(f"{name}.npy", "w") as member:
                if name in header:
                    np.lib.format.write_array_header_1_0(
                        member,
                        {"descr": "<f8", "fortran_order": False, "shape": header[name]},
                    )
                    member.write(b"\0" * 80)
                else:
                    np.lib.format.write_array(member, np.asarray(array), allow_pickle=False)


@contextmanager
def memory_cap(limit: int):
    """The address space of this process capped at ``limit`` bytes more than it uses now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as statm:
        used = int(statm.read().split()[0]) * resource.getpagesize()
    resource.setrlimit(resource.RLIMIT_AS, (used + limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


@pytest.mark.parametrize(("key", "shape"), [("adam_m", (400_000_000,)), ("theta", (10**11,))])
def test_a_huge_declared_shape_is_refused_before_it_is_allocated(es_runs, tmp_path, key, shape):
    """A header declaring 400M or 1e11 floats (3.2 GB, 800 GB) over 80 bytes of data."""
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    with np.load(path) as saved:
        arrays = {k: saved[k] for k in saved.files}
    fake_npz(path, arrays, {key: shape})
    with memory_cap(2**31):  # less than the declared array
        message = refused_by_evaluate(run_dir)
    assert_one_line(message, str(path), key, f"shape {shape}")


# ---------------------------------------------------------------------------------- not such a file
@contextmanager
def deadline(seconds: int):
    """Fail instead of hanging: SIGALRM after ``seconds`` raises in the blocked call."""

    def expired(signum, frame):
        raise TimeoutError(f"still reading after {seconds} s: the read blocks")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize("reader", ["evaluate", "init"])
def test_a_fifo_as_the_learner_state_is_refused_at_once(es_runs, tmp_path, reader):
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    path.unlink()
    os.mkfifo(path)
    with deadline(60):
        if reader == "evaluate":
            message = refused_by_evaluate(run_dir)
        else:
            message = refused_by_init("net_es", run_dir, tmp_path)
    assert_one_line(message, str(path), "FIFO", "not a regular file")


def test_a_fifo_as_metrics_json_is_refused_by_the_report_at_once(es_runs, tmp_path):
    run_dir = copy_run(es_runs, "reserve_es", tmp_path)
    path = run_dir / "metrics.json"
    path.unlink()
    os.mkfifo(path)
    with deadline(60), pytest.raises(UserError) as err:
        build_report([run_dir], tmp_path / "report")
    assert_one_line(str(err.value), str(path), "FIFO")


def test_metrics_json_linked_to_dev_zero_is_refused_without_reading_it(es_runs, tmp_path):
    """In a process of at most 2 GB of memory and 60 s: reading /dev/zero would take both."""
    run_dir = copy_run(es_runs, "reserve_es", tmp_path)
    path = run_dir / "metrics.json"
    path.unlink()
    path.symlink_to("/dev/zero")
    code = (
        "import resource, sys\n"
        "hard = resource.getrlimit(resource.RLIMIT_AS)[1]\n"
        "resource.setrlimit(resource.RLIMIT_AS, (2**31, hard))\n"
        "from mrta_rl.config import UserError\n"
        "from mrta_rl.run_layout import read_metrics\n"
        "try:\n"
        f"    read_metrics(__import__('pathlib').Path({str(path)!r}))\n"
        "except UserError as err:\n"
        "    print(err)\n"
        "    sys.exit(0)\n"
        "sys.exit(1)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr[-500:]
    assert_one_line(done.stdout, str(path), "character device", "not a regular file")


def test_a_huge_sparse_file_as_the_learner_state_is_called_too_big(es_runs, tmp_path):
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    path.unlink()
    with open(path, "wb") as handle:
        handle.truncate(3 * 10**9)  # 3 GB of holes: no disk used
    message = refused_by_evaluate(run_dir)
    assert_one_line(message, str(path), "more than the limit of")
    assert "pickle" not in message


def test_a_link_to_a_text_file_as_the_learner_state_is_called_what_it_is(es_runs, tmp_path):
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    path.unlink()
    path.symlink_to("/etc/passwd")
    message = refused_by_evaluate(run_dir)
    assert_one_line(message, str(path), "not an npz archive")
    assert "pickle" not in message


def test_init_from_weights_of_another_size_is_one_short_line(es_runs, tmp_path):
    """The run's network has 16 hidden units, the saved one 8: no list of every weight's name."""
    source = finished_run(
        tmp_path / "small", [*NET_ES, "learner.hidden=8", "train.episodes=1"], "net_es"
    )
    message = refused_by_init("net_es", source, tmp_path)
    assert_one_line(message, str(state_path(source, "net_es")), "theta", "(358,)")


def test_resume_refuses_a_checkpoint_with_a_negative_second_moment(tmp_path):
    cfg = compose_config([*RESERVE_ES, "train.episodes=3", "train.checkpoint_every=1"])
    save_hydra_files(cfg, tmp_path, "reserve_es", "system1")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ReserveESLearner, "end_episode", stop_after(ReserveESLearner.end_episode, 2))
        with pytest.raises(Stopped):
            train(cfg, run_dir=tmp_path)
    HydraConfig.instance().cfg = None
    path = state_path(latest_checkpoint(tmp_path), "reserve_es")
    with np.load(path) as saved:
        rewrite(path, adam_v=-saved["adam_v"] - 1.0)
    with pytest.raises(UserError) as err:
        resume(tmp_path)
    assert_one_line(str(err.value), str(path), "adam_v", "must be >= 0")


# ---------------------------------------------------------------------------------- text files
def test_a_team_file_with_a_syntax_error_is_one_line_naming_file_and_line(tmp_path):
    path = tmp_path / "team.yaml"
    path.write_text("name: mine\nrobots:\n  R1: [T1, T2\n  R2: [T2]\n")
    with pytest.raises(UserError) as err:
        use_team_files([f"system={path}"])
    assert_one_line(str(err.value), str(path), "line 4", "YAML syntax error")


@pytest.mark.parametrize(
    ("content", "said"), [("", "got empty"), ("root:x:0:0:root:/root:/bin/bash\n", "got a str")]
)
def test_a_team_file_that_is_no_mapping_is_one_line_naming_the_file(tmp_path, content, said):
    """An empty file, or a link to a text file (/etc/passwd reads as one string): the message
    names the file as typed, not the link's target."""
    path, target = tmp_path / "team.yaml", tmp_path / "passwd"
    target.write_text(content)
    path.symlink_to(target)
    with pytest.raises(UserError) as err:
        use_team_files([f"system={path}"])
    assert_one_line(str(err.value), str(path), "a team must be a mapping", said)


def test_a_curve_cell_that_is_not_a_number_names_the_file_and_line(tmp_path):
    path = tmp_path / "curve.csv"
    path.write_text("env_ticks,episode,team_return_mean\n1,1,abc\n")
    with pytest.raises(UserError) as err:
        read_curve(path)
    assert_one_line(str(err.value), str(path), "line 2", "team_return_mean 'abc' is not a number")


# ---------------------------------------------------------------------------------- rollout bases
def rollout_dir(run_dir: Path, base: Path) -> Path:
    """A rollout run dir (its config files) whose base is ``base``."""
    cfg = compose_config(
        ["learner=rollout", "system=system1", "debug=smoke", f"learner.base={base}"]
    )
    save_hydra_files(cfg, run_dir, "rollout", "system1")
    HydraConfig.instance().cfg = None
    return run_dir


def test_a_rollout_run_that_is_its_own_base_is_one_line(tmp_path):
    own = rollout_dir(tmp_path / "own", tmp_path / "own")
    code, _, err = train_script(tmp_path / "run", "learner=rollout", f"learner.base={own}")
    assert_user_error(code, err, "learner.base", str(own), "its own base")
    assert_one_line(err)
    assert not (tmp_path / "run").exists()


def test_rollout_bases_that_loop_are_one_line(tmp_path):
    first, second = tmp_path / "first", tmp_path / "second"
    rollout_dir(first, second)
    rollout_dir(second, first)
    with pytest.raises(UserError) as err:
        train(
            compose_config(["learner=rollout", *ES[:2], f"learner.base={first}"]),
            run_dir=tmp_path / "run",
        )
    HydraConfig.instance().cfg = None
    assert_one_line(str(err.value), "learner.base", "loop", str(first), str(second))


# ---------------------------------------------------------------------------------- NaN updates
class Stopped(BaseException):
    """Stands for a kill after an episode."""


def stop_after(end_episode, episodes: int):
    """``end_episode`` that stops the run (as a kill would) after ``episodes`` ES steps."""

    def wrapped(self):
        end_episode(self)
        if self.steps == episodes:
            raise Stopped

    return wrapped


def poison_update(update, episode: int):
    """``update`` that leaves a NaN in Adam's first moment during ``episode``: that episode's ES
    step makes the weights NaN (whatever the gradient: a smoke episode's may be zero)."""

    def wrapped(self, *args, **kwargs):
        if self.steps == episode - 1:
            self._adam_m = np.full_like(self._adam_m, math.nan)
        return update(self, *args, **kwargs)

    return wrapped


def resume(run_dir: Path) -> dict:
    cfg = compose_config([f"resume={run_dir}"])
    HydraConfig.instance().cfg = None  # as from the command line: no overrides but resume=
    try:
        return train(cfg)
    finally:
        HydraConfig.instance().cfg = None


def test_an_update_to_nan_stops_the_run_and_keeps_the_last_checkpoint(tmp_path):
    overrides = [*RESERVE_ES, "train.episodes=4", "train.checkpoint_every=1"]
    cut_dir, full_dir = tmp_path / "cut", tmp_path / "full"
    cfg = compose_config(overrides)
    save_hydra_files(cfg, cut_dir, "reserve_es", "system1")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ReserveESLearner, "update", poison_update(ReserveESLearner.update, 3))
        with pytest.raises(UserError) as err:
            train(cfg, run_dir=cut_dir)
    HydraConfig.instance().cfg = None
    assert_one_line(str(err.value), "reserve-ES", "ES step 3", "NaN", "last checkpoint")
    checkpoint = latest_checkpoint(cut_dir)
    assert checkpoint is not None and checkpoint.name == "2"
    with np.load(state_path(checkpoint, "reserve_es")) as saved:
        assert np.isfinite(saved["theta"]).all() and int(saved["steps"]) == 2
    assert not (cut_dir / "metrics.json").exists() and not (cut_dir / "learner").exists()
    resumed = resume(cut_dir)
    full = train(compose_config(overrides), run_dir=full_dir)
    HydraConfig.instance().cfg = None
    assert without_timings(resumed) == without_timings(full)
    assert json.loads((cut_dir / "metrics.json").read_text())["train"]["episodes"] == 4


# ---------------------------------------------------------------------------------- torch learners
QMIX = [
    "learner=qmix",
    "system=system1",
    "debug=smoke",
    "train.episodes=3",
    "train.checkpoint_every=1",
    "learner.warmup_frames=100",
    "learner.hidden=16",
    "learner.batch_size=32",
]


@pytest.fixture(scope="module")
def stopped_qmix(tmp_path_factory) -> Path:
    """A qmix run stopped after its checkpoint of episode 2 (gradient steps made)."""
    run_dir = tmp_path_factory.mktemp("qmix") / "cut"
    cfg = compose_config(QMIX)
    save_hydra_files(cfg, run_dir, "qmix", "system1")
    save = TrainingCheckpoint.save

    def save_then_stop(self, loop, files=None):
        path = save(self, loop, files)
        if loop["episode"] == 2:
            raise Stopped
        return path

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(TrainingCheckpoint, "save", save_then_stop)
        with pytest.raises(Stopped):
            train(cfg, run_dir=run_dir)
    HydraConfig.instance().cfg = None
    return run_dir


OPTIMIZER_FAULTS = {
    "negative second moment": ("exp_avg_sq", lambda t: -t - 1.0, "must be >= 0"),
    "negative step": ("step", lambda t: t * 0 - 5, "must be >= 0"),
    "NaN first moment": ("exp_avg", lambda t: t * math.nan, "NaN or infinite"),
}


@pytest.mark.parametrize("case", sorted(OPTIMIZER_FAULTS))
def test_a_damaged_optimizer_state_is_refused_on_resume(stopped_qmix, tmp_path, case):
    key, damage, reason = OPTIMIZER_FAULTS[case]
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_qmix, run_dir)
    path = latest_checkpoint(run_dir) / "training.pt"
    extra = torch.load(path, weights_only=True)
    state = extra["optimizer"]["state"]
    assert state, "no gradient step was made before the checkpoint"
    first = next(iter(state))
    state[first][key] = damage(state[first][key])
    torch.save(extra, path)
    with pytest.raises(UserError) as err:
        resume(run_dir)
    assert_one_line(str(err.value), str(path), f"optimizer.state.{first}.{key}", reason)


def test_a_nan_loss_stops_a_torch_learner_before_its_step(stopped_qmix, tmp_path, monkeypatch):
    """The replayed rewards made NaN: the loss is NaN; the step it would feed is not taken."""
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_qmix, run_dir)
    process_batch = QMIXLearner.process_batch

    def poisoned(self, data):
        data = process_batch(self, data)
        return data.apply(lambda t: t * math.nan if t.is_floating_point() else t)

    monkeypatch.setattr(QMIXLearner, "process_batch", poisoned)
    with pytest.raises(UserError) as err:
        resume(run_dir)
    assert_one_line(str(err.value), "QMIX", "gradient step", "the loss is nan", "last checkpoint")
    assert latest_checkpoint(run_dir).name == "2"
    assert not (run_dir / "learner").exists()


# ---------------------------------------------------------------------------------- the fuzz
FUZZ = settings(
    max_examples=14,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
EVAL_METRICS = "eval_metrics.json"  # what a re-evaluation adds to the run dir
ES_ARRAYS = ("theta", "adam_m", "adam_v")  # the float arrays of an ES state
MEMBERS = (*ES_ARRAYS, "steps", "features")
# values written into a float array: out of range, at the bounds, and ordinary ones
VALUES = (math.nan, math.inf, -math.inf, 1e308, -1e308, 1e9, -1e9, 1e18, -1.0, -0.0, 5e-324, 2.5)
DTYPES = ("float16", "float32", ">f8", "longdouble", "complex128", "int64", "uint8", "bool")
DTYPES += ("object", "<U3", ">U20", "S20", "datetime64[s]")
POSITION = st.integers(0, 2**32)  # where in the file (taken modulo its length) or a seed
DAMAGES = st.one_of(
    st.tuples(
        st.just("value"),
        st.sampled_from(ES_ARRAYS),
        st.sampled_from(["one", "all"]),
        st.sampled_from(VALUES),
    ),
    st.tuples(st.just("steps"), st.sampled_from([-5, 0, 2, 2**62, 2**63 - 1, 2**64 - 1])),
    st.tuples(st.just("dtype"), st.sampled_from(MEMBERS), st.sampled_from(DTYPES)),
    st.tuples(
        st.just("shape"),
        st.sampled_from(MEMBERS),
        st.sampled_from(["column", "scalar", "shorter", "longer", "empty", "row"]),
    ),
    st.tuples(
        st.just("member"),
        st.sampled_from(MEMBERS),
        st.sampled_from(["missing", "extra", "renamed", "duplicate", "in_a_folder"]),
    ),
    st.tuples(st.just("names"), st.sampled_from(["renamed", "swapped", "padded", "another"])),
    st.tuples(
        st.just("bytes"), st.sampled_from(["truncated", "flipped", "random", "empty"]), POSITION
    ),
    st.tuples(
        st.just("zip"),
        st.sampled_from(
            ["deflated", "deflated_flipped", "lzma_flipped", "method", "encrypted", "reordered"]
        ),
        POSITION,
    ),
    st.tuples(
        st.just("header"),
        st.sampled_from(MEMBERS),
        st.sampled_from([(10**11,), (400_000_000,), (-1,), (2**62, 2**62), ()]),
    ),
)


def convert(array: np.ndarray, dtype: str) -> np.ndarray:
    """``array`` as ``dtype``; zeros of that dtype where numpy cannot convert it (text to int)."""
    try:
        return array.astype(dtype)
    except (TypeError, ValueError):
        return np.zeros(array.shape, dtype)


def reshaped(array: np.ndarray, how: str) -> np.ndarray:
    flat = array.reshape(-1)
    return {
        "column": flat[:, None],
        "scalar": flat[0] if flat.size else np.zeros((), array.dtype),
        "shorter": flat[:-1],
        "longer": np.concatenate([flat, flat[:1]]) if flat.size else np.zeros(1, array.dtype),
        "empty": flat[:0],
        "row": flat[None, :],
    }[how]


def write_zip(path: Path, members: list, method: int = zipfile.ZIP_STORED) -> None:
    """An npz of ``(member name, array)`` pairs, compressed with ``method``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a duplicate member name is the damage wanted
        with zipfile.ZipFile(path, "w", compression=method) as archive:
            for name, array in members:
                with archive.open(name, "w") as member:
                    np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=True)


def flip(path: Path, position: int) -> None:
    data = bytearray(path.read_bytes())
    data[position % len(data)] ^= 0x5A
    path.write_bytes(bytes(data))


def set_central_directory(path: Path, offset: int, fmt: str, value: int) -> None:
    """A field (``offset`` bytes into each central directory entry) of every member set."""
    data = bytearray(path.read_bytes())
    entry = data.find(b"PK\x01\x02")
    while entry >= 0:
        struct.pack_into(fmt, data, entry + offset, value)
        entry = data.find(b"PK\x01\x02", entry + 4)
    path.write_bytes(bytes(data))


def damage_state(path: Path, damage: tuple) -> None:
    """Apply one drawn damage (:data:`DAMAGES`) to a learner state file."""
    kind, *how = damage
    with np.load(path) as saved:
        arrays = {f"{k}.npy": saved[k] for k in saved.files}
    if kind == "value":
        name, where, value = how
        array = arrays[f"{name}.npy"]
        if where == "one":
            array[len(array) // 2] = value
        else:
            array[:] = value
    elif kind == "steps":
        arrays["steps.npy"] = np.array(how[0])  # int64, or uint64 past it
    elif kind == "dtype":
        arrays[f"{how[0]}.npy"] = convert(arrays[f"{how[0]}.npy"], how[1])
    elif kind == "shape":
        arrays[f"{how[0]}.npy"] = reshaped(arrays[f"{how[0]}.npy"], how[1])
    elif kind == "member":
        name, what = f"{how[0]}.npy", how[1]
        array = arrays.pop(name)
        renamed = {"extra": name, "renamed": f"x{name}", "in_a_folder": f"learner/{name}"}
        if what in renamed:
            arrays[renamed[what]] = array
        if what == "extra":
            arrays["extra.npy"] = np.zeros(3)
        if what == "duplicate":
            write_zip(path, [*arrays.items(), (name, array), (name, array)])
            return
    elif kind == "names":
        names = arrays["features.npy"].copy()
        if how[0] == "renamed":
            names[0] = "bias_renamed"
        elif how[0] == "swapped":
            names[[0, 1]] = names[[1, 0]]
        elif how[0] == "padded":
            names = np.char.add(names, " ")
        else:  # the other learner's names
            other = ReserveESLearner if len(names) != N_FEATURES else NetESLearner
            names = np.asarray(other.weight_names)
        arrays["features.npy"] = names
    elif kind == "header":
        fake_npz(path, {k.removesuffix(".npy"): v for k, v in arrays.items()}, {how[0]: how[1]})
        return
    if kind == "bytes":
        what, position = how
        if what == "truncated":
            path.write_bytes(path.read_bytes()[: position % path.stat().st_size])
        elif what == "flipped":
            flip(path, position)
        elif what == "random":
            path.write_bytes(random.Random(position).randbytes(position % 5000))
        else:
            path.write_bytes(b"")
        return
    if kind == "zip":
        what, position = how
        methods = {"deflated": zipfile.ZIP_DEFLATED, "lzma": zipfile.ZIP_LZMA}
        method = methods.get(what.split("_")[0], zipfile.ZIP_STORED)
        if what == "reordered":
            arrays = dict(reversed(arrays.items()))
        write_zip(path, list(arrays.items()), method)
        if what.endswith("flipped"):
            flip(path, 30 + position % (path.stat().st_size - 30))  # past the first header
        elif what == "method":
            set_central_directory(path, 10, "<H", 99)  # a compression method zip lacks
        elif what == "encrypted":
            set_central_directory(path, 8, "<H", 1)  # flag bit 0: encrypted
        return
    write_zip(path, list(arrays.items()))


def readable_as_saved(path: Path, pristine: Path) -> bool | None:
    """Whether numpy reads ``path`` as the same arrays as ``pristine`` (None: it cannot read it)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with np.load(path) as damaged, np.load(pristine) as saved:
                if sorted(damaged.files) != sorted(saved.files):
                    return False
                return all(
                    damaged[k].shape == saved[k].shape
                    and damaged[k].dtype.kind == saved[k].dtype.kind
                    and np.array_equal(damaged[k], saved[k])
                    for k in saved.files
                )
    except Exception:  # noqa: BLE001 - numpy's reader is the yardstick, whatever it raises
        return None


def digest(folder: Path) -> str:
    """Hash of every file's path and bytes below ``folder``, but a re-evaluation's metrics."""
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and p.name != EVAL_METRICS):
        h.update(str(path.relative_to(folder)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def undamaged(es_runs, tmp_path_factory) -> dict[str, dict]:
    """What evaluating each ES run and starting a run from it (``init=``) give, undamaged."""
    results = {}
    for learner in es_runs:
        run_dir = copy_run(es_runs, learner, tmp_path_factory.mktemp("undamaged"))
        results[learner] = {
            "evaluate": evaluation(evaluate_checkpoint(run_dir)),
            "init": without_timings(started_from(learner, run_dir, run_dir.parent / "init")),
        }
    return results


def evaluation(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k != "checkpoint"}  # the run dir evaluated


def started_from(learner: str, source: Path, run_dir: Path) -> dict:
    overrides = NET_ES if learner == "net_es" else RESERVE_ES
    try:
        return train(compose_config([*overrides, f"init={source}"]), run_dir=run_dir)
    finally:
        HydraConfig.instance().cfg = None


def refused_or_undamaged(call, path: Path, same: bool | None, expected: dict) -> str:
    """``call()`` ends as the undamaged state's (when the damage changed nothing numpy reads)
    or is refused in one short line naming the file."""
    try:
        result = call()
    except NonFiniteState as err:  # init=: a state within its ranges whose ES step leaves them
        assert_one_line(str(err), "ES step", "training stopped")
        return "stopped"
    except UserError as err:
        assert_one_line(str(err), str(path))
        return "refused"
    assert same is not None, "accepted a file numpy itself cannot read"
    if same:
        assert result == expected
    return "accepted"


def test_fuzz_es_state_through_evaluate_and_init(es_runs, undamaged, tmp_path_factory):
    """A damaged ``learner/<learner>.npz``: evaluated and started from (``init=``) as the
    undamaged file is when the damage changes nothing numpy reads, else refused naming the file
    by both; the fuzz saw both outcomes. The examples are what the fuzz found: each was a
    traceback, a warning or a message naming the folder, not the file."""
    outcomes = collections.Counter()

    @FUZZ
    @given(learner=st.sampled_from(["net_es", "reserve_es"]), damage=DAMAGES)
    @example("net_es", ("steps", 2**63 - 1))  # OverflowError saving the next step's count
    @example("reserve_es", ("steps", 2**64 - 1))  # as uint64: the same
    @example("net_es", ("zip", "deflated_flipped", 9))  # zlib.error
    @example("net_es", ("zip", "lzma_flipped", 11))  # LZMAError
    @example("reserve_es", ("zip", "method", 0))  # NotImplementedError, naming the folder only
    @example("net_es", ("zip", "encrypted", 0))  # RuntimeError, naming the folder only
    @example("net_es", ("dtype", "theta", "float16"))  # RuntimeWarning of the range check
    def one_case(learner, damage):
        run_dir = copy_run(es_runs, learner, tmp_path_factory.mktemp("fuzz"))
        path = state_path(run_dir, learner)
        damage_state(path, damage)
        same = readable_as_saved(path, state_path(es_runs[learner], learner))
        expected, init_dir = undamaged[learner], run_dir.parent / "init"
        before = digest(run_dir)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # no numpy overflow chatter either
            evaluated = refused_or_undamaged(
                lambda: evaluation(evaluate_checkpoint(run_dir)),
                path,
                same,
                expected["evaluate"],
            )
            started = refused_or_undamaged(
                lambda: without_timings(started_from(learner, run_dir, init_dir)),
                path,
                same,
                expected["init"],
            )
        assert digest(run_dir) == before, "the damaged run dir changed"
        if evaluated == "refused":  # the same checks guard both paths, before any output
            assert started == "refused", damage
            assert not init_dir.exists() and not (run_dir / EVAL_METRICS).exists()
        outcomes[evaluated] += 1

    one_case()
    assert outcomes["refused"] >= 8 and outcomes["accepted"] >= 2, outcomes


def test_a_state_that_does_not_decompress_is_one_line_from_the_evaluate_script(es_runs, tmp_path):
    """What the fuzz found, as a user meets it: a traceback of zlib before, one line now."""
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    damage_state(path, ("zip", "deflated_flipped", 9))
    before = digest(run_dir)
    proc = script("evaluate.py", f"checkpoint={run_dir}")
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, str(path), "truncated or damaged")
    assert_one_line(err)
    assert digest(run_dir) == before
