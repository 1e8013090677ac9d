"""Every file a run reads is checked: damaged, hostile or odd files are refused in one line.

The learner state files of ``net_es`` and ``reserve_es`` (``learner/*.npz``) through ``init=``,
``resume=`` and ``scripts/evaluate.py``; FIFOs, devices, huge and foreign files where a run's
file should be; a team file with a YAML syntax error; a curve.csv cell that is not a number; a
rollout base that is its own base; an update that makes the weights NaN. Each is refused with
one short line naming the file (or the learner and step) and the culprit, never hangs, never
reads without bound, and leaves what was there (a checkpoint) usable.
"""

from __future__ import annotations

import json
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.core.hydra_config import HydraConfig

from mrta_rl.commands import use_team_files
from mrta_rl.config import UserError
from mrta_rl.learners.neural.qmix import QMIXLearner
from mrta_rl.learners.search.reserve_es import ReserveESLearner
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


def test_a_fifo_as_the_learner_state_is_refused_at_once(es_runs, tmp_path):
    run_dir = copy_run(es_runs, "net_es", tmp_path)
    path = state_path(run_dir, "net_es")
    path.unlink()
    os.mkfifo(path)
    with deadline(60):
        message = refused_by_evaluate(run_dir)
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
