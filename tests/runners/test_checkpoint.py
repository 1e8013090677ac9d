"""Run dirs are data: unique per run, never overwritten, never executed, checked on load, and
training survives interruption (checkpoints, Ctrl-C, resume=)."""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf, open_dict

from mrta_rl.envs import AuctionEnv
from mrta_rl.run_layout import RunDirError
from mrta_rl.runners import build_run, evaluate_checkpoint, train
from mrta_rl.runners.checkpoint import TrainingCheckpoint, latest_checkpoint
from mrta_rl.runners.validation import learner_class

ROOT = Path(__file__).resolve().parents[2]
# measured, not computed (labels_per_s: a teaching learner's planner, labels per second spent)
TIMINGS = ("wall_s", "collect_s", "train_s", "fps_collection", "fps_training", "fps_overall")
TIMINGS = (*TIMINGS, "labels_per_s")


def script(*args: str, cwd: Path = ROOT, **kwargs) -> subprocess.Popen:
    """``python <script> args`` with this checkout's package first on the path."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def save_hydra_files(cfg, run_dir: Path, learner: str, system: str) -> None:
    """What Hydra writes into a run dir before training (config and group choices)."""
    hydra_dir = run_dir / ".hydra"
    hydra_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, hydra_dir / "config.yaml")
    choices = {"hydra": {"runtime": {"choices": {"learner": learner, "system": system}}}}
    OmegaConf.save(OmegaConf.create(choices), hydra_dir / "hydra.yaml")


def without_timings(metrics: dict) -> dict:
    metrics = json.loads(json.dumps(metrics))
    for key in TIMINGS:
        metrics["train"].pop(key, None)
    metrics.pop("resources", None)  # wall time and peak memory of the run, measured
    metrics["eval"].pop("decision_time", None)  # a learner's measured time per decision
    return metrics


# ---------------------------------------------------------------------------------- unique dirs
def test_runs_started_together_get_their_own_dirs(tmp_path):
    """Four runs started at once: four run dirs, four metrics.json."""
    runs = [
        script(str(ROOT / "scripts" / "train.py"), "learner=greedy", "debug=smoke", cwd=tmp_path)
        for _ in range(4)
    ]
    for run in runs:
        _, err = run.communicate(timeout=300)
        assert run.returncode == 0, err
    metrics = sorted((tmp_path / "outputs").rglob("metrics.json"))
    assert len(metrics) == 4
    assert len({m.parent for m in metrics}) == 4
    assert all(m.parent.name.split("_")[-2] == "greedy" for m in metrics)  # <time>_greedy_<id>


def test_a_finished_run_is_never_overwritten(compose_cfg, tmp_path):
    cfg = compose_cfg(["learner=greedy", "system=system1", "debug=smoke"])
    first = train(cfg, run_dir=tmp_path)
    again = compose_cfg(["learner=random", "system=system1", "debug=smoke"])
    with pytest.raises(ValueError, match="metrics.json"):
        train(again, run_dir=tmp_path)
    assert json.loads((tmp_path / "metrics.json").read_text()) == first


@pytest.mark.parametrize("value", ["-1", "abc", "true"])
def test_bad_checkpoint_interval_fails_before_work(compose_cfg, tmp_path, value):
    cfg = compose_cfg(["learner=greedy", "debug=smoke", f"train.checkpoint_every={value}"])
    with pytest.raises(ValueError, match="train.checkpoint_every"):
        train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_run_dir_with_a_checkpoint_is_only_resumed(compose_cfg, tmp_path):
    (tmp_path / "checkpoint").mkdir()
    with pytest.raises(ValueError, match=f"resume={tmp_path}"):
        train(compose_cfg(["learner=greedy", "debug=smoke"]), run_dir=tmp_path)


# ---------------------------------------------------------------------------------- plain data
@pytest.fixture
def greedy_run(compose_cfg, tmp_path) -> Path:
    cfg = compose_cfg(["learner=greedy", "system=system1", "debug=smoke"])
    run_dir = tmp_path / "run"
    save_hydra_files(cfg, run_dir, "greedy", "system1")
    train(cfg, run_dir=run_dir)
    return run_dir


def tamper(run_dir: Path, key: str, value) -> None:
    path = run_dir / ".hydra" / "config.yaml"
    cfg = OmegaConf.load(path)
    with open_dict(cfg):
        OmegaConf.update(cfg, key, value, force_add=True)
    OmegaConf.save(cfg, path)


def test_a_tampered_run_config_executes_nothing(greedy_run, tmp_path):
    """A run config naming a callable (here: one that truncates a file) is never instantiated."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    tamper(
        greedy_run,
        "learner.min_visits",
        {"_target_": "builtins.open", "_args_": [str(victim), "w"]},
    )
    with pytest.raises(ValueError, match=r"learner\.min_visits"):
        evaluate_checkpoint(greedy_run)
    assert victim.read_text() == "precious"
    assert not (greedy_run / "eval_metrics.json").exists()


@pytest.mark.parametrize(
    ("key", "value", "culprit"),
    [
        ("learner._target_", "builtins.exec", r"learner\._target_"),
        ("learner._target_", "mrta_rl.envs.AuctionEnv", r"learner\._target_"),
        ("learner._target_", "mrta_rl.learners.NoSuchLearner", r"learner\._target_"),
        ("learner.reserve", {"a": 1}, r"learner\.reserve"),
        ("logger._target_", "os.system", r"logger\._target_"),
        ("env.horizon", {"_target_": "os.getcwd"}, r"env\.horizon\._target_"),
        ("system.name", "${oc.env:HOME}", r"system\.name"),
    ],
)
def test_run_config_holds_plain_data_only(greedy_run, key, value, culprit):
    """Only learner and logger classes of this package; plain values everywhere else."""
    tamper(greedy_run, key, value)
    with pytest.raises(ValueError, match=culprit):
        evaluate_checkpoint(greedy_run)


# ---------------------------------------------------------------------------------- damaged tables
@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    """subG-CQL trained one smoke episode on System-I and on System-II (run dirs)."""
    from tests.conftest import compose_config

    dirs = {}
    for system in ("system1", "system2"):
        cfg = compose_config(
            ["learner=subg_cql", f"system={system}", "debug=smoke", "train.episodes=1"]
        )
        run_dir = tmp_path_factory.mktemp(system)
        save_hydra_files(cfg, run_dir, "subg_cql", system)
        train(cfg, run_dir=run_dir)
        dirs[system] = run_dir
    HydraConfig.instance().cfg = None  # the next test composes its own config
    return dirs


def fresh_copy(run_dir: Path, tmp_path: Path) -> Path:
    import shutil

    target = tmp_path / "copy"
    shutil.copytree(run_dir, target)
    (target / "metrics.json").unlink()
    return target


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def random_bytes(path: Path) -> None:
    path.write_bytes(np.random.default_rng(0).bytes(4096))


def shorten(path: Path) -> None:
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    name = next(k for k in arrays if k.endswith(".codes"))
    arrays[name] = arrays[name][:-5]
    np.savez_compressed(path, **arrays)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (truncate, "truncated or damaged"),
        (random_bytes, "not a table file"),
        (shorten, r"codes|joint actions"),
    ],
)
def test_damaged_tables_are_named_before_evaluation(trained, tmp_path, damage, message):
    run_dir = fresh_copy(trained["system1"], tmp_path)
    table = run_dir / "learner" / "q_tables.npz"
    damage(table)
    with pytest.raises(ValueError, match=message) as err:
        evaluate_checkpoint(run_dir)
    assert str(table) in str(err.value)
    assert "pickle" not in str(err.value) and "unsafe" not in str(err.value)
    assert not (run_dir / "eval_metrics.json").exists()


def test_tables_of_another_system_are_refused(trained, tmp_path):
    run_dir = fresh_copy(trained["system2"], tmp_path)
    import shutil

    shutil.rmtree(run_dir / "learner")
    shutil.copytree(trained["system1"] / "learner", run_dir / "learner")
    with pytest.raises(ValueError, match="another team") as err:
        evaluate_checkpoint(run_dir)
    assert str(run_dir / "learner" / "team.json") in str(err.value)


@pytest.mark.parametrize("damage", [truncate, random_bytes])
def test_damaged_weights_are_named_without_suggesting_unsafe_loading(compose_cfg, tmp_path, damage):
    cfg = compose_cfg(["learner=qmix", "system=system1", "debug=smoke"])
    learner = build_run(cfg).learner
    learner.save(tmp_path)
    damage(tmp_path / "weights.pt")
    with pytest.raises(ValueError, match="weights.pt") as err:
        build_run(cfg).learner.load(tmp_path)
    assert "weights_only" not in str(err.value) and "unsafe" not in str(err.value)


def test_weights_of_another_shape_are_refused(compose_cfg, tmp_path):
    small = build_run(compose_cfg(["learner=qmix", "system=system1", "learner.hidden=8"]))
    small.learner.save(tmp_path)
    run = build_run(compose_cfg(["learner=qmix", "system=system1"]))
    with pytest.raises(ValueError, match=r"weights.pt: tensor .* expected"):
        run.learner.load(tmp_path)


# ---------------------------------------------------------------------------------- kill and resume
# Kill and resume across processes: whatever a checkpoint lacks is lost with the killed process.
CHECKPOINT_LINE = re.compile(r"checkpoint after episode (\d+) in ")  # TrainingCheckpoint.save
RESUME_LINE = re.compile(r"resuming from .* after episode (\d+)")  # TrainingCheckpoint.restore


def learner_kind(name: str) -> str:
    """The ``kind`` of the learner class ``conf/learner/<name>.yaml`` builds."""
    return learner_class(
        yaml.safe_load((ROOT / "conf" / "learner" / f"{name}.yaml").read_text())
    ).kind


def learner_cls(name: str) -> type:
    """The learner class ``conf/learner/<name>.yaml`` builds."""
    return learner_class(yaml.safe_load((ROOT / "conf" / "learner" / f"{name}.yaml").read_text()))


KINDS = {path.stem: learner_kind(path.stem) for path in (ROOT / "conf" / "learner").glob("*.yaml")}
TRAINED = sorted(name for name, kind in KINDS.items() if kind != "fixed")


def budget(name: str) -> list[str]:
    """The kill-and-resume budget of a learner: its own, its regime's, then its kind's."""
    if name in BUDGETS:
        return BUDGETS[name]
    if getattr(learner_cls(name), "on_policy", False):
        return BUDGETS["on_policy"]
    return BUDGETS[KINDS[name]]


# budgets per kind: long enough that a kill lands well before the end, short enough for seconds
# (a smoke episode takes a few ms on the numpy loop, a few hundred ms on the TorchRL loop)
BUDGETS = {
    "tabular": ["train.episodes=300", "train.checkpoint_every=10"],
    "search": ["train.episodes=150", "train.checkpoint_every=10"],
    # gradient steps from the second episode on, epsilon decayed over the run (so a resumed run
    # that restarts the schedule explores differently); small networks keep the steps quick
    "neural": [
        "train.episodes=6",
        "train.checkpoint_every=1",
        "learner.warmup_frames=200",
        "learner.eps_decay_frames=1000",
        "learner.hidden=32",
        "learner.batch_size=64",
    ],
    # mappo, ippo: a PPO update every 25 ticks of the smoke horizon (debug_learner/smoke)
    "on_policy": ["train.episodes=6", "train.checkpoint_every=1"],
    # a planner that labels (its generator) and soft labels; the base's own labels first,
    # DAgger's mix decaying over the run (a resumed run that restarts either differs)
    "expert_iteration": [
        "train.episodes=6",
        "train.checkpoint_every=1",
        "learner.warmup_frames=200",
        "learner.imitate_base_frames=400",
        "learner.beta_decay_frames=1000",
        "learner.batch_size=64",
        "learner.samples=2",
        "learner.horizon=4",
        "learner.soft_targets=0.5",
    ],
}


def setting(args: list[str], key: str) -> int:
    return int(next(a.split("=")[1] for a in args if a.startswith(f"{key}=")))


def wait_for_checkpoint(run: subprocess.Popen, log: Path, episode: int) -> int:
    """Poll the run's ``train.log`` until a checkpoint of ``episode`` or later is complete.

    Returns:
        The episode of the last complete checkpoint seen.
    """
    deadline = time.monotonic() + 120
    while True:
        done = [int(n) for n in CHECKPOINT_LINE.findall(log.read_text() if log.is_file() else "")]
        if done and done[-1] >= episode:
            return done[-1]
        assert run.poll() is None, f"ended before the checkpoint of episode {episode}"
        assert time.monotonic() < deadline, f"no checkpoint of episode {episode} in {log}"
        time.sleep(0.005)


def killed_at_checkpoint(args: list[str], cut_dir: Path, episode: int) -> int:
    """Start ``train.py args`` in ``cut_dir``, SIGKILL it once the checkpoint of ``episode`` (or
    later) is complete; the episode of the last complete checkpoint."""
    cut = script("scripts/train.py", *args, f"hydra.run.dir={cut_dir}")
    killed_after = wait_for_checkpoint(cut, cut_dir / "train.log", episode)
    cut.send_signal(signal.SIGKILL)
    cut.wait()
    return killed_after


def assert_same_learner_state(a: Path, b: Path) -> None:
    """The learner/ dirs of two runs hold the same tables or weights, bit for bit."""
    names = sorted(p.name for p in (a / "learner").iterdir())
    assert names == sorted(p.name for p in (b / "learner").iterdir())
    for name in names:
        x, y = a / "learner" / name, b / "learner" / name
        if x.suffix == ".npz":
            with np.load(x) as p, np.load(y) as q:
                assert sorted(p.files) == sorted(q.files)
                assert all(np.array_equal(p[k], q[k]) for k in p.files), name
        elif x.suffix == ".pt":
            p, q = (torch.load(f, weights_only=True) for f in (x, y))
            assert p.keys() == q.keys() and all(torch.equal(p[k], q[k]) for k in p), name
        else:
            assert x.read_text() == y.read_text(), name


def assert_same_run(full_dir: Path, cut_dir: Path) -> None:
    """Same metrics.json (timings aside), curve.csv and saved tables or weights."""
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (full_dir, cut_dir))
    assert without_timings(b) == without_timings(a)
    assert (cut_dir / "curve.csv").read_text() == (full_dir / "curve.csv").read_text()
    assert_same_learner_state(full_dir, cut_dir)
    assert not (cut_dir / "checkpoint").exists()  # removed once the run is complete


def spent_before(cut_dir: Path) -> dict:
    """What the run had spent at its current checkpoint (``loop.spent`` of training.json)."""
    loop = json.loads((latest_checkpoint(cut_dir) / "training.json").read_text())["loop"]
    return loop.get("spent", {})


def assert_whole_life(cut_dir: Path, spent: dict) -> None:
    """The resumed run's figures count the share of the killed process (no magnitudes timed)."""
    metrics = json.loads((cut_dir / "metrics.json").read_text())
    train_info, resources = metrics["train"], metrics["resources"]
    assert train_info["wall_s"] >= round(spent["wall_s"], 3) > 0
    assert resources["wall_s"] >= round(spent["run_wall_s"], 3) > 0
    assert resources["wall_s"] >= train_info["wall_s"] - 1e-3  # the run holds its training
    assert resources["cpu_s"] >= round(spent["cpu_s"], 3) > 0
    for part in ("collect_s", "train_s"):  # the neural loops': fps are frames over their totals
        if part in train_info:
            assert train_info[part] >= round(spent[part], 3)
    if "fps_collection" in train_info:
        frames = train_info["env_ticks"]
        collect_s = max(train_info["collect_s"], 1e-3)  # rounded to the ms, as fps to 0.1
        assert train_info["fps_collection"] == pytest.approx(frames / collect_s, rel=1e-2)


def resumed_run(resumed: subprocess.Popen, cut_dir: Path) -> int:
    """Wait for ``train.py resume=<cut_dir>`` to succeed; the episode it resumed after."""
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err + out
    assert "Traceback" not in err + out
    return int(RESUME_LINE.findall((cut_dir / "train.log").read_text())[-1])


@pytest.mark.parametrize(
    "learner",
    # the TorchRL loop's cases take about 10 s each (two processes starting torch)
    [pytest.param(n, marks=[pytest.mark.slow] * (budget(n) is BUDGETS["neural"])) for n in TRAINED],
)
def test_sigkill_after_a_random_checkpoint_then_resume_ends_like_an_uninterrupted_run(
    compose_cfg, tmp_path, learner
):
    """Every trained learner kind resumes exactly in a new process.

    The uninterrupted run trains in this process while the resumed one starts up beside it.
    """
    args = [f"learner={learner}", "system=system1", "debug=smoke", *budget(learner)]
    episodes, every = setting(args, "train.episodes"), setting(args, "train.checkpoint_every")
    # the checkpoint to kill after, at random, seeded by the case: one in the first two thirds
    target = random.Random(learner).randrange(every, 2 * episodes // 3, every)
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    killed_after = killed_at_checkpoint(args, cut_dir, target)
    assert not (cut_dir / "metrics.json").exists()
    spent = spent_before(cut_dir)  # the killed process's share, recorded in the checkpoint
    resumed = script("scripts/train.py", f"resume={cut_dir}")
    train(compose_cfg(args), run_dir=full_dir)
    resumed_after = resumed_run(resumed, cut_dir)
    assert killed_after <= resumed_after < episodes
    assert_same_run(full_dir, cut_dir)
    assert_whole_life(cut_dir, spent)


@pytest.mark.slow  # about 10 s: two processes starting torch
def test_a_run_killed_with_a_full_replay_buffer_resumes_to_the_same_end(compose_cfg, tmp_path):
    """The buffer (300 transitions) is full and has wrapped by the checkpoint resumed from."""
    args = ["learner=qmix", "system=system1", "debug=smoke", *BUDGETS["neural"]]
    args.append("learner.buffer_size=300")  # 200 frames per smoke episode
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    killed_at_checkpoint(args, cut_dir, 3)
    replay = torch.load(latest_checkpoint(cut_dir) / "replay.pt", weights_only=True)
    assert {leaf.shape[0] for leaf in tensor_values(replay["transitions"])} == {300}
    resumed = script("scripts/train.py", f"resume={cut_dir}")
    train(compose_cfg(args), run_dir=full_dir)
    assert 3 <= resumed_run(resumed, cut_dir) < setting(args, "train.episodes")
    assert_same_run(full_dir, cut_dir)


class WorkClock:
    """A fake ``time.perf_counter`` and ``time.process_time``: time moves by 2**-10 s at each
    env step (the work), and stands still otherwise. Two runs that step the same number of
    times take the same time on it, whatever the machine's load."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def work_clock(monkeypatch) -> WorkClock:
    clock = WorkClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    monkeypatch.setattr(time, "process_time", clock)
    step = AuctionEnv.step

    def timed_step(self, *args, **kwargs):
        clock.now += 2**-10
        return step(self, *args, **kwargs)

    monkeypatch.setattr(AuctionEnv, "step", timed_step)
    return clock


@pytest.mark.parametrize(
    "learner",
    # one learner per training loop: the tick loop, the TorchRL loop, the on-policy loop
    ["dql", "qmix", "mappo"],
)
def test_a_resumed_run_reports_the_time_of_its_whole_life(
    compose_cfg, tmp_path, monkeypatch, work_clock, learner
):
    """Stopped after its second episode (as by Ctrl-C), then resumed: on the work clock, its
    training and run times, CPU time and frames per second are the uninterrupted run's."""
    # the work clock needs no long run: a few episodes, a checkpoint after each
    rest = [a for a in budget(learner) if not a.startswith(("train.episodes=", "train.check"))]
    args = [f"learner={learner}", "system=system1", "debug=smoke", *rest]
    args += ["train.episodes=6", "train.checkpoint_every=1"]
    full = train(compose_cfg(args), run_dir=tmp_path / "full")
    episode_end = TrainingCheckpoint.episode_end

    def stop_after_two(self, loop, last, files=None):
        self.stop_requested = self.stop_requested or loop["episode"] >= 2
        return episode_end(self, loop, last, files)

    monkeypatch.setattr(TrainingCheckpoint, "episode_end", stop_after_two)
    cut_dir = tmp_path / "cut"
    cfg = compose_cfg(args)
    save_hydra_files(cfg, cut_dir, learner, "system1")
    with pytest.raises(SystemExit) as stop:
        train(cfg, run_dir=cut_dir)
    assert stop.value.code == 130
    monkeypatch.setattr(TrainingCheckpoint, "episode_end", episode_end)
    spent = spent_before(cut_dir)
    cfg = compose_cfg([f"resume={cut_dir}"])
    HydraConfig.instance().cfg = None  # as from the command line: no overrides but resume=
    resumed = train(cfg)
    for key in ("wall_s", "collect_s", "train_s", "fps_collection", "fps_training", "fps_overall"):
        assert resumed["train"].get(key) == full["train"].get(key), key
    for key in ("wall_s", "cpu_s"):
        assert resumed["resources"][key] == full["resources"][key], key
    assert resumed["train"]["wall_s"] > spent["wall_s"] > 0  # both processes trained
    assert_whole_life(cut_dir, spent)


def test_resume_refuses_other_overrides(compose_cfg, tmp_path):

    with pytest.raises(ValueError, match="train.episodes"):
        train(compose_cfg([f"resume={tmp_path}", "train.episodes=3"]))


def test_ctrl_c_saves_says_where_and_exits_130(tmp_path):
    run_dir = tmp_path / "run"
    run = script(
        "scripts/train.py",
        "learner=subg_cql",
        "system=system1",
        "debug=smoke",
        "train.episodes=100000",
        f"hydra.run.dir={run_dir}",
    )
    curve = run_dir / "curve.csv"
    deadline = time.monotonic() + 120
    while not (curve.is_file() and len(curve.read_text().splitlines()) > 2):
        assert run.poll() is None and time.monotonic() < deadline, run.communicate()
        time.sleep(0.1)
    run.send_signal(signal.SIGINT)
    out, err = run.communicate(timeout=120)
    err += out  # Hydra logs to stdout
    assert run.returncode == 130, err
    assert "Traceback" not in err
    assert f"checkpoint saved in {run_dir / 'checkpoint'}" in err
    assert f"resume={run_dir}" in err
    state = json.loads((latest_checkpoint(run_dir) / "training.json").read_text())
    assert state["loop"]["episode"] >= 2 and not (run_dir / "metrics.json").exists()


@pytest.mark.parametrize(
    "learner",
    ["subg_cql", pytest.param("qmix", marks=pytest.mark.slow)],  # qmix: about 10 s
)
def test_sigterm_saves_says_where_exits_143_and_resumes_to_the_same_end(
    compose_cfg, tmp_path, learner
):
    """SIGTERM (a scheduler preempting the job) is the first Ctrl-C: save, say where, stop."""
    budget = [a for a in BUDGETS[KINDS[learner]] if not a.startswith("train.checkpoint_every=")]
    args = [f"learner={learner}", "system=system1", "debug=smoke", *budget]
    episodes = setting(args, "train.episodes")
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    # no periodic checkpoints: the one resumed from is the one SIGTERM asks for
    cut = script("scripts/train.py", *args, "train.checkpoint_every=0", f"hydra.run.dir={cut_dir}")
    curve = cut_dir / "curve.csv"
    deadline = time.monotonic() + 120
    while not (curve.is_file() and len(curve.read_text().splitlines()) > 2):
        assert cut.poll() is None and time.monotonic() < deadline, cut.communicate()
        time.sleep(0.005)
    cut.send_signal(signal.SIGTERM)
    out, err = cut.communicate(timeout=120)
    err += out  # Hydra logs to stdout
    assert cut.returncode == 143, err
    assert "Traceback" not in err
    assert f"checkpoint saved in {cut_dir / 'checkpoint'}" in err
    assert f"resume={cut_dir}" in err
    assert (latest_checkpoint(cut_dir) / "training.json").is_file()
    assert not (cut_dir / "metrics.json").exists()
    resumed = script("scripts/train.py", f"resume={cut_dir}")
    train(compose_cfg(args), run_dir=full_dir)
    assert resumed_run(resumed, cut_dir) < episodes
    assert_same_run(full_dir, cut_dir)


# ---------------------------------------------------------------------------------- replay files
@pytest.fixture(scope="module")
def killed_qmix(tmp_path_factory) -> tuple[Path, dict]:
    """A qmix run killed after its checkpoint of episode 2 (which holds a replay.pt), and the
    metrics of the same run uninterrupted."""
    from tests.conftest import compose_config

    args = ["learner=qmix", "system=system1", "debug=smoke", *BUDGETS["neural"]]
    cut_dir = tmp_path_factory.mktemp("qmix") / "cut"
    killed_at_checkpoint(args, cut_dir, 2)
    # the filled rows only (a few hundred transitions of ~4 kB), not the capacity's 50,000
    assert (latest_checkpoint(cut_dir) / "replay.pt").stat().st_size < 20 * 2**20
    full = train(compose_config(args), run_dir=tmp_path_factory.mktemp("qmix") / "full")
    GlobalHydra.instance().clear()
    HydraConfig.instance().cfg = None
    return cut_dir, full


REPLAY_DAMAGES = ("none", "empty", "drop", "extra", "retype", "reshape", "nan", "cut", "garbage")


def tensor_values(tree: dict) -> list[torch.Tensor]:
    """The tensors of a nested dict (a replay file's team keys hold rows and a count)."""
    return [
        v
        for value in tree.values()
        for v in (tensor_values(value) if isinstance(value, dict) else [value])
        if isinstance(v, torch.Tensor)
    ]


def tensor_leaves(tree: dict, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    keys = []
    for name, value in tree.items():
        if isinstance(value, dict):
            keys += tensor_leaves(value, (*prefix, name))
        else:
            keys.append((*prefix, name))
    return keys


def damage_replay(path: Path, damage: str, data) -> str | None:
    """Damage a checkpoint's replay.pt as drawn; the key the refusal must name (None: any)."""
    if damage in ("cut", "garbage"):
        content = path.read_bytes()
        if damage == "cut":
            content = content[: data.draw(st.integers(0, len(content) - 1), label="length")]
        else:
            content = data.draw(st.binary(max_size=2048), label="bytes")
        path.write_bytes(content)
        return None
    payload = torch.load(path, weights_only=True)
    leaves = [("transitions", *key) for key in tensor_leaves(payload["transitions"])]

    def value(key: tuple[str, ...]):
        node = payload
        for name in key:
            node = node[name]
        return node

    targets = {
        "drop": [("torch_rng",), ("transitions",), *leaves],
        "retype": [("torch_rng",), ("transitions",), *leaves],
        "reshape": [("torch_rng",), *(k for k in leaves if isinstance(value(k), torch.Tensor))],
        "nan": [
            k for k in leaves if isinstance(value(k), torch.Tensor) and value(k).is_floating_point()
        ],
    }.get(damage, [("extra",)])
    key = data.draw(st.sampled_from(targets), label="key")
    *parents, name = key
    node = value(parents)
    if damage == "empty":
        payload, key = {}, ("torch_rng",)  # the message lists the keys expected
    elif damage == "drop":
        del node[name]
    elif damage == "extra":
        node[name] = torch.zeros(3)
    elif damage == "retype":
        node[name] = data.draw(
            st.sampled_from([3, "x", [1, 2], None, torch.zeros(2, dtype=torch.float64)]),
            label="value",
        )
    elif damage == "reshape":
        shape = data.draw(st.sampled_from(["a row fewer", "a trailing dim"]), label="shape")
        node[name] = node[name][:-1] if shape == "a row fewer" else node[name][..., None]
    elif damage == "nan":
        flat = node[name].reshape(-1).clone()
        flat[data.draw(st.integers(0, flat.numel() - 1), label="at")] = float("nan")
        node[name] = flat.reshape(node[name].shape)
    torch.save(payload, path)
    return ".".join(key)


def files_of(run_dir: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}


@pytest.mark.slow  # about 10 s: the killed run, its reference, ten resumes
@settings(
    max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_a_damaged_replay_file_is_refused_naming_it(killed_qmix, compose_cfg, data):
    """``resume=`` on a checkpoint whose replay.pt is damaged: refused naming the file and key,
    no file changed; an intact one is accepted and ends like the uninterrupted run."""
    cut_dir, full = killed_qmix
    damage = data.draw(st.sampled_from(REPLAY_DAMAGES), label="damage")
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        shutil.copytree(cut_dir, run_dir)
        path = latest_checkpoint(run_dir) / "replay.pt"
        key = damage_replay(path, damage, data) if damage != "none" else None
        before = files_of(run_dir)
        cfg = compose_cfg([f"resume={run_dir}"])
        HydraConfig.instance().cfg = None  # as from the command line: no overrides but resume=
        try:
            metrics = train(cfg)
        except RunDirError as err:
            assert damage != "none", err
            assert str(path) in str(err)
            assert key is None or key in str(err), (key, str(err))
            assert files_of(run_dir) == before
        else:
            assert damage == "none", damage
            assert without_timings(metrics) == without_timings(full)


@pytest.mark.slow  # about 10 s with the killed run it copies
def test_an_empty_replay_file_gets_one_line_and_exit_2(killed_qmix, tmp_path):
    """The script's side of the refusal: ``error: ...`` naming the file, no traceback."""
    run_dir = tmp_path / "run"
    shutil.copytree(killed_qmix[0], run_dir)
    path = latest_checkpoint(run_dir) / "replay.pt"
    torch.save({}, path)
    before = files_of(run_dir)
    resumed = script("scripts/train.py", f"resume={run_dir}")
    _, err = resumed.communicate(timeout=120)
    assert resumed.returncode == 2, err
    assert err.startswith("error: ") and str(path) in err and "Traceback" not in err
    assert {k: v for k, v in files_of(run_dir).items() if k != "train.log"} == {
        k: v for k, v in before.items() if k != "train.log"
    }


def test_a_reevaluation_on_more_copies_keeps_the_first_episodes(greedy_run):
    """episodes=N batch_size=N: episode b is copy b's first episode, as in the run's evaluation."""
    first = json.loads((greedy_run / "metrics.json").read_text())["eval"]["team_return"]
    again = evaluate_checkpoint(greedy_run, episodes=4, batch_size=4)["eval"]["team_return"]
    assert len(again["per_episode"]) == 4
    assert again["per_episode"][:2] == first["per_episode"]  # smoke: 2 episodes in one round
    rounds = evaluate_checkpoint(greedy_run, episodes=4)["eval"]["team_return"]  # 2 rounds of 2
    assert rounds["per_episode"][:2] == first["per_episode"]
    assert rounds["per_episode"][2:] != again["per_episode"][2:]  # second episodes of copies 0, 1


@pytest.mark.parametrize("rows", [3, 6])
def test_a_full_replay_buffer_is_saved_without_a_copy_and_a_filling_one_as_its_rows(tmp_path, rows):
    """A copy of a full buffer would double a large run's peak memory during the save; a filling
    buffer's slice is a view of the whole storage, so only its rows are copied and written."""
    from tensordict import TensorDict

    from mrta_rl.learners.neural.torch_learner import LoopSettings
    from mrta_rl.runners.replay import LoopBuffer

    settings = LoopSettings(
        2, buffer_size=4, minibatch_size=2, updates_per_batch=1, warmup_frames=0
    )
    loop_buffer = LoopBuffer(
        settings, on_policy=False, device=torch.device("cpu"), episode_frames=8
    )
    loop_buffer.extend(TensorDict({"obs": torch.arange(rows * 2.0).reshape(rows, 2)}, [rows]))
    saved = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(torch, "save", lambda payload, path: saved.append(payload))
        loop_buffer.save(tmp_path / "replay.pt")
    obs = saved[0]["transitions"]["team"]["rows"]["obs"]
    storage = next(iter(loop_buffer.buffers.values())).storage._storage["obs"]
    assert obs.tolist() == storage[: min(rows, 4)].tolist()
    if rows > 4:  # full: the storage itself
        assert obs.data_ptr() == storage.data_ptr()
    else:  # filling: its rows, not the capacity's
        assert obs.untyped_storage().nbytes() == rows * 2 * obs.element_size()
