"""One process per run dir, claimed before Hydra writes; checkpoints atomic at every instant.

A refused run changes nothing: a finished run's files stay byte-identical, a refused ``resume=``
creates nothing; a second process on a live run's dir is refused at once, naming the holder; a
save killed at any filesystem step leaves the newest complete checkpoint to resume from.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mrta_rl.run_layout import RunDirError
from mrta_rl.runners import build_run, train
from mrta_rl.runners.checkpoint import TrainingCheckpoint, latest_checkpoint
from mrta_rl.runners.run_dir import run_dir_of

ROOT = Path(__file__).resolve().parents[2]


def script(*args: str, cwd: Path = ROOT) -> subprocess.Popen:
    """``python scripts/train.py args`` with this checkout's package first on the path."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["PYTHONPATH"] = str(ROOT)
    return subprocess.Popen(
        [sys.executable, str(ROOT / "scripts" / "train.py"), *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc: subprocess.Popen, timeout: float = 300) -> tuple[int, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, err + out


def assert_refused(code: int, err: str, *named: str) -> None:
    assert code == 2, err
    assert err.startswith("error: ") and "Traceback" not in err, err
    for text in named:
        assert text in err, err


def digest(folder: Path) -> dict[str, str]:
    """Every file and folder under ``folder`` -> hash of its bytes ('dir' for a folder)."""
    return {
        str(p.relative_to(folder)): "dir"
        if p.is_dir()
        else hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
    }


# ---------------------------------------------------------------------------------- claiming
@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["hydra.run.dir=/tmp/x", "learner=greedy"], (Path("/tmp/x"), False)),
        (["resume=runs/a"], (Path("runs/a"), True)),
        (["resume=null", "hydra.run.dir=b"], (Path("b"), False)),
        (["-m", "hydra.run.dir=/tmp/x", "seed=0,1"], None),  # sweep jobs get their own dirs
        (["--cfg", "job", "hydra.run.dir=/tmp/x"], None),  # no job runs
        (["learner=greedy"], None),  # the default dir is unique to the process
        (["hydra.run.dir=out/${now:%H}"], None),  # Hydra resolves it
        (["multirun/x", "--out", "y"], None),  # an argparse script (report.py)
        (["-c"], None),  # Hydra's parse reports it
    ],
)
def test_the_run_dir_is_read_from_the_command_line(args, expected):
    assert run_dir_of(args) == expected


# ---------------------------------------------------------------------------------- refused runs
def test_a_refused_run_leaves_a_finished_run_byte_identical(compose_cfg, tmp_path):
    """hydra.run.dir=<finished run>: refused before Hydra replaces its .hydra/ snapshot."""
    run_dir = tmp_path / "run"
    cfg = compose_cfg(["learner=greedy", "system=system1", "debug=smoke"])
    (run_dir / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    (run_dir / "train.log").write_text("the finished run's log\n")
    train(cfg, run_dir=run_dir)
    before = digest(run_dir)
    again = script(
        "learner=random", "system=system2", "seed=7", "debug=smoke", f"hydra.run.dir={run_dir}"
    )
    resumed = script(f"resume={run_dir}")
    for proc in (again, resumed):
        assert_refused(*finish(proc), f"{run_dir} already holds the results of a finished run")
    assert digest(run_dir) == before


# ---------------------------------------------------------------------------------- refused resumes
def test_a_refused_resume_leaves_nothing(tmp_path):
    """resume= of a new, an empty dir or /: refused, no dir made, no train.log anywhere."""
    new, empty, cwd = tmp_path / "new" / "run", tmp_path / "empty", tmp_path / "cwd"
    empty.mkdir()
    cwd.mkdir()
    root_log = Path("/train.log")
    root_log_before = root_log.exists()
    procs = {
        new: script(f"resume={new}", cwd=cwd),
        empty: script(f"resume={empty}", cwd=cwd),
        Path("/"): script("resume=/", cwd=cwd),
    }
    for target, proc in procs.items():
        assert_refused(*finish(proc), f"resume={target}: not a run dir of scripts/train.py")
    assert not (tmp_path / "new").exists()
    assert list(empty.iterdir()) == [] and list(cwd.iterdir()) == []
    assert root_log.exists() == root_log_before


# ---------------------------------------------------------------------------------- live runs
def test_a_live_runs_dir_is_refused_to_a_second_process(tmp_path):
    """resume= and a fresh run on a live run's dir: refused at once, naming its pid; the lock
    dies with the run (SIGKILL)."""
    run_dir = tmp_path / "run"
    live = script(
        "learner=subg_cql",
        "system=system1",
        "debug=smoke",
        "train.episodes=100000",
        "train.checkpoint_every=1",
        f"hydra.run.dir={run_dir}",
    )
    deadline = time.monotonic() + 240
    while True:
        assert live.poll() is None and time.monotonic() < deadline, live.communicate()
        try:
            if latest_checkpoint(run_dir) is not None:
                break
        except RunDirError:  # between two saves
            pass
        time.sleep(0.1)
    second = [
        script(f"resume={run_dir}"),
        script("learner=greedy", "debug=smoke", f"hydra.run.dir={run_dir}"),
    ]
    try:
        for proc in second:
            code, err = finish(proc, timeout=120)
            assert_refused(code, err, f"{run_dir} is in use by another process (pid {live.pid})")
            assert "interrupted" not in err
        assert live.poll() is None  # the live run goes on
    finally:
        live.send_signal(signal.SIGKILL)
        live.wait()
    code, err = finish(script("learner=greedy", "debug=smoke", f"hydra.run.dir={run_dir}"))
    assert_refused(
        code, err, f"holds the checkpoint of an interrupted run: continue it with resume={run_dir}"
    )


# ---------------------------------------------------------------------------------- atomic saves
class Crash(BaseException):
    """Stands for SIGKILL at one filesystem step of a save: nothing after it runs."""


FILESYSTEM_STEPS = [
    (os, "mkdir"),
    (os, "rename"),
    (os, "replace"),
    (os, "fsync"),
    (os, "unlink"),
    (os, "rmdir"),
    (shutil, "rmtree"),
]


def crash_at(monkeypatch, step: int) -> None:
    """Raise :class:`Crash` at the ``step``-th call of any filesystem step."""
    calls = itertools.count()
    for module, name in FILESYSTEM_STEPS:
        real = getattr(module, name)

        def failing(*args, _real=real, **kwargs):
            if next(calls) == step:
                raise Crash
            return _real(*args, **kwargs)

        monkeypatch.setattr(module, name, failing)


EPISODES = 10  # train.episodes of the checkpoints below


def save(learner, run_dir: Path, episode: int) -> None:
    """A checkpoint whose loop state and loop file both say which episode it is."""
    checkpoint = TrainingCheckpoint(learner, run_dir, every=1, resume=False, episodes=EPISODES)

    def files(folder: Path) -> None:
        (folder / "loop_file.txt").write_text(f"episode {episode}")

    curve = [{"episode": i + 1, "env_ticks": 0, "team_return_mean": 0.0} for i in range(episode)]
    checkpoint.save({"episode": episode, "env_ticks": 0, "curve": curve}, files)


def resumed_episode(cfg, run_dir: Path) -> int | None:
    """The episode a new process resumes from (None: no checkpoint), checked complete."""
    learner = build_run(cfg).learner
    try:
        loop = TrainingCheckpoint(
            learner, run_dir, every=1, resume=True, episodes=EPISODES
        ).restore()
    except RunDirError as err:
        assert "holds no training checkpoint" in str(err), err
        return None
    episode = loop["episode"]
    assert len(loop["curve"]) == episode
    assert (latest_checkpoint(run_dir) / "loop_file.txt").read_text() == f"episode {episode}"
    return episode


@pytest.mark.parametrize("earlier", [0, 1], ids=["first_save", "second_save"])
def test_a_save_killed_at_any_step_leaves_the_newest_complete_checkpoint(
    compose_cfg, tmp_path, monkeypatch, earlier
):
    cfg = compose_cfg(["learner=subg_cql", "system=system1", "debug=smoke"])
    learner = build_run(cfg).learner
    outcomes = []
    for step in itertools.count():
        run_dir = tmp_path / f"step{step}"
        if earlier:
            save(learner, run_dir, earlier)
        crash_at(monkeypatch, step)
        try:
            save(learner, run_dir, earlier + 1)
            crashed = False
        except Crash:
            crashed = True
        monkeypatch.undo()
        episode = resumed_episode(cfg, run_dir)
        assert episode in ((earlier or None), earlier + 1)
        outcomes.append(episode)
        if crashed:  # the run goes on after a resume: the next save completes
            save(learner, run_dir, earlier + 2)
            assert resumed_episode(cfg, run_dir) == earlier + 2
        else:
            assert episode == earlier + 1
            break
    # the newest complete one: the earlier checkpoint until the new one is complete, then it
    switch = outcomes.index(earlier + 1)
    assert set(outcomes[:switch]) == {earlier or None} and set(outcomes[switch:]) == {earlier + 1}
    assert switch >= 4  # crashes before the pointer moved were tried
    assert len(outcomes) - switch >= 2  # and after it moved (removing the older version)
    assert (
        json.loads((latest_checkpoint(run_dir) / "training.json").read_text())["loop"]["episode"]
        == earlier + 1
    )
