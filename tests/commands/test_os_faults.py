"""Operating-system faults end a command in one line naming the path and the cause, exit 2.

A full disk, a file size limit (``ulimit -f``), a folder that cannot be written or a file where
a folder goes are the machine's refusals, not bugs: the commands say so in one ``error:`` line
(``mrta_rl/errors.py``), and the newest complete training checkpoint stays usable. The faults
are real: ``RLIMIT_FSIZE`` in the child process, writes into ``/dev/full`` through a symlink,
and (as root, with ``chattr``) immutable folders.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from mrta_rl.errors import user_message
from mrta_rl.runners import build_run, train
from mrta_rl.runners.checkpoint import TrainingCheckpoint, latest_checkpoint
from mrta_rl.runners.learner_state import save_learner
from tests.commands.test_arguments import assert_one_line, run
from tests.commands.test_cli import ROOT
from tests.commands.test_inputs import copy_run, finished_run  # noqa: F401 (a fixture)
from tests.runners.test_checkpoint import assert_same_run

FULL = Path("/dev/full")  # every write fails with ENOSPC
needs_dev_full = pytest.mark.skipif(not FULL.exists(), reason="needs /dev/full (Linux)")


def chattr_works(tmp_path_factory: pytest.TempPathFactory) -> bool:
    probe = tmp_path_factory.mktemp("chattr")
    if shutil.which("chattr") is None:
        return False
    if subprocess.run(["chattr", "+i", str(probe)], capture_output=True).returncode != 0:
        return False
    subprocess.run(["chattr", "-i", str(probe)], check=True)
    return True


@pytest.fixture(scope="module")
def can_chattr(tmp_path_factory) -> bool:
    return chattr_works(tmp_path_factory)


@contextmanager
def immutable(folder: Path, can_chattr: bool) -> Iterator[None]:
    """``folder`` cannot be written, even by root (``chattr +i``), inside the block."""
    if not can_chattr:
        pytest.skip("needs chattr +i (root on a file system with attributes)")
    subprocess.run(["chattr", "+i", str(folder)], check=True)
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


# ---------------------------------------------------------------------------------- train
def test_a_file_size_limit_is_one_line_naming_the_file_and_leaves_no_run_dir(tmp_path):
    """``ulimit -f``: Hydra's first write in the run dir fails (File too large)."""
    run_dir = tmp_path / "run"
    limit = 512  # bytes: below the size of .hydra/config.yaml
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "scripts" / "train.py"), "learner=greedy", "system=system1"]
        + ["debug=smoke", f"hydra.run.dir={run_dir}"],
        env={k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
        | {"PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)),
    )
    _, err = proc.communicate(timeout=300)
    assert_one_line(proc.returncode, err, f"error: {run_dir / '.hydra' / 'config.yaml'}: ")
    assert "File too large (EFBIG)" in err
    assert not run_dir.exists()  # only Hydra's files were in it: removed


@needs_dev_full
def test_a_full_disk_keeps_the_last_checkpoint_and_the_run_resumes_to_the_same_end(
    compose_cfg, tmp_path
):
    """The final learner state hits a full disk: one line; the checkpoint of episode 2 stays."""
    args = ["learner=subg_cql", "system=system1", "debug=smoke", "train.episodes=3"]
    cut_dir, full_dir = tmp_path / "cut", tmp_path / "full"
    tables = cut_dir / "learner" / "q_tables.npz"
    tables.parent.mkdir(parents=True)
    tables.symlink_to(FULL)
    code, _, err = run(
        "train.py", *args, "train.checkpoint_every=1", f"hydra.run.dir={cut_dir}", cwd=tmp_path
    )
    assert_one_line(code, err, f"error: {tables}: No space left on device (ENOSPC)")
    version = latest_checkpoint(cut_dir)
    assert version == cut_dir / "checkpoint" / "2"
    assert json.loads((version / "training.json").read_text())["loop"]["episode"] == 2
    assert not (cut_dir / "metrics.json").exists()
    tables.unlink()  # space again
    code, _, err = run("train.py", f"resume={cut_dir}", cwd=tmp_path)
    assert code == 0, err
    train(compose_cfg([*args, "train.checkpoint_every=1"]), run_dir=full_dir)
    assert_same_run(full_dir, cut_dir)


@needs_dev_full
def test_a_log_file_on_a_full_disk_stops_the_run_in_one_line(tmp_path):
    """logging would print a traceback per line it cannot write, and go on."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "train.log").symlink_to(FULL)
    code, _, err = run("train.py", "learner=greedy", "debug=smoke", f"hydra.run.dir={run_dir}")
    assert_one_line(code, err, f"error: {run_dir / 'train.log'}: No space left on device (ENOSPC)")
    assert not (run_dir / "metrics.json").exists()


def fail_on(target: str, fault: int):
    """A stand-in for ``os.replace`` that refuses to write ``target`` (a file name)."""
    real = os.replace

    def replace(src, dst, *args, **kwargs):
        if Path(dst).name == target:
            raise OSError(fault, os.strerror(fault), str(dst))
        return real(src, dst, *args, **kwargs)

    return replace


@pytest.mark.parametrize(
    "refused",
    ["training.json", "latest"],  # a file of the new version; the pointer to it
)
def test_a_refused_checkpoint_write_leaves_the_last_complete_one(
    compose_cfg, tmp_path, monkeypatch, refused
):
    run = build_run(compose_cfg(["learner=subg_cql", "system=system1", "debug=smoke"]))
    saver = TrainingCheckpoint(run.learner, tmp_path, every=1, resume=False, episodes=5)
    row = {"env_ticks": 0, "episode": 1, "team_return_mean": 0.0}
    saver.save({"episode": 1, "curve": [row]})
    monkeypatch.setattr(os, "replace", fail_on(refused, errno.ENOSPC))
    with pytest.raises(OSError) as caught:
        saver.save({"episode": 2, "curve": [row, {**row, "episode": 2}]})
    assert user_message(caught.value).endswith(f"{refused}: No space left on device (ENOSPC)")
    monkeypatch.undo()
    root = tmp_path / "checkpoint"
    assert latest_checkpoint(tmp_path) == root / "1"
    left = {p.name for p in root.iterdir()}
    # nothing half-written is left: an unnamed complete version at most, removed by the next save
    assert left == {"1", "latest"} | ({"2"} if refused == "latest" else set())
    saver.save({"episode": 3, "curve": [row] * 3})
    assert {p.name for p in root.iterdir()} == {"3", "latest"}


def test_a_run_dir_that_is_a_file_is_one_line(tmp_path):
    path = tmp_path / "results.txt"
    path.write_text("keep me\n")
    code, _, err = run("train.py", "learner=greedy", "debug=smoke", f"hydra.run.dir={path}")
    assert_one_line(code, err, f"error: {path}: File exists (EEXIST)")
    assert path.read_text() == "keep me\n"


def test_a_run_dir_in_a_folder_that_cannot_be_written_is_one_line(tmp_path, can_chattr):
    folder = tmp_path / "locked"
    folder.mkdir()
    with immutable(folder, can_chattr):
        code, _, err = run(
            "train.py", "learner=greedy", "debug=smoke", f"hydra.run.dir={folder / 'run'}"
        )
    assert_one_line(code, err, f"error: {folder / 'run'}: Operation not permitted (EPERM)")
    assert list(folder.iterdir()) == []


@needs_dev_full
def test_torch_writes_on_a_full_disk_name_the_file(compose_cfg, tmp_path):
    pytest.importorskip("torchrl")
    run_setup = build_run(compose_cfg(["learner=qmix", "system=system1", "debug=smoke"]))
    (tmp_path / "weights.pt").symlink_to(FULL)
    with pytest.raises(Exception) as caught:  # torch raises a RuntimeError during the OSError
        save_learner(run_setup.learner, tmp_path)
    assert user_message(caught.value) == (
        f"{tmp_path / 'weights.pt'}: No space left on device (ENOSPC)"
    )


# ---------------------------------------------------------------------------------- evaluate
def test_evaluate_checks_it_can_write_before_it_evaluates(
    finished_run,  # noqa: F811 (the fixture)
    tmp_path,
    can_chattr,
):
    run_dir = copy_run(finished_run, tmp_path / "run")
    with immutable(run_dir, can_chattr):
        code, out, err = run("evaluate.py", f"checkpoint={run_dir}")
    assert_one_line(
        code, err, f"error: eval_metrics.json: cannot write in {run_dir}: Operation not permitted"
    )
    assert out == ""  # no summary: nothing was evaluated
    assert not (run_dir / "eval_metrics.json").exists()


# ---------------------------------------------------------------------------------- others
@needs_dev_full
def test_bench_output_on_a_full_disk_is_one_line(tmp_path):
    out = tmp_path / "bench.json"
    out.symlink_to(FULL)
    args = ["--systems", "system1", "--paths", "step", "--batch-sizes", "1", "--threads", "1"]
    args += ["--repeats", "1", "--seconds", "0.01", "--out", str(out)]
    code, _, err = run("bench_env.py", *args)
    assert code == 2 and "Traceback" not in err, err
    # after the progress bar of the benchmark: the fault comes with the write, after the work
    assert err.rstrip("\n").splitlines()[-1] == f"error: {out}: No space left on device (ENOSPC)"


def test_report_into_a_folder_that_cannot_be_written_is_refused_first(
    finished_run,  # noqa: F811 (the fixture)
    tmp_path,
    can_chattr,
):
    folder = tmp_path / "reports"
    folder.mkdir()
    with immutable(folder, can_chattr):
        code, out, err = run("report.py", str(finished_run), "--out", str(folder / "r"))
    assert_one_line(code, err, f"error: --out: cannot write in {folder}: Operation not permitted")
    assert out == "" and list(folder.iterdir()) == []


def test_a_json_write_that_hits_the_file_size_limit_leaves_no_temporary_file(tmp_path):
    """``write_json`` is atomic: a write that fails (File too large) leaves neither file."""
    code = (
        "import resource, sys\n"
        "from pathlib import Path\n"
        "from mrta_rl.run_layout import write_json\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (100, 100))\n"
        "try:\n"
        f"    write_json(Path({str(tmp_path)!r}) / 'm.json', {{'x': list(range(1000))}})\n"
        "except OSError as err:\n"
        "    print(err.errno)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        env=os.environ | {"PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.stdout.strip() == "27", done.stderr  # EFBIG
    assert list(tmp_path.iterdir()) == []
