"""The package as a library user gets it: the wheel, installed apart from the repository.

The wheel is built from a copy of the sources (no download, no build files left in the
repository) and installed into a fresh virtual environment that sees the test environment's
packages (torch, torchrl...) through a ``.pth`` file but not the repository: no ``PYTHONPATH``,
and every command runs in a temporary directory outside it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("mrta-train", "mrta-evaluate", "mrta-report", "mrta-partition", "mrta-bench")
TEAM = """\
name: my_team
robots:             # robot -> task types it can do
  R1: [T1, T2]
  R2: [T2]
  R3: [T1, T3]
"""
GYM_CHECK = """\
import sys
import gymnasium as gym
import mrta_rl.envs
print(mrta_rl.envs.__file__)
for env_id, kwargs in [
    ("mrta_rl/Auction-System1-v0", {}),
    ("mrta_rl/Auction-System2-v0", {}),
    ("mrta_rl/Auction-v0", {"system": sys.argv[1]}),
]:
    env = gym.make(env_id, **kwargs)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    print(env_id, env.unwrapped.core.system.n_robots, float(reward))
"""


def _run(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    done = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{args}:\n{done.stdout}\n{done.stderr}"
    return done


def copy_sources(source: Path) -> None:
    """Only what a wheel is built from (the package, conf/, the build backend): no .venv,
    outputs or build files."""
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    build_system = tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]
    for name in ("mrta_rl", "conf", *build_system.get("backend-path", [])):
        shutil.copytree(ROOT / name, source / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)


def files_below(folder: Path) -> list[Path]:
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if "__pycache__" not in p.parts)


def test_building_a_wheel_leaves_the_sources_as_they_were(tmp_path):
    """``pip wheel .`` in a clone: the wheel in the output folder, no build/ or egg-info left."""
    source = tmp_path / "clone"
    copy_sources(source)
    before = files_below(source)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    pip = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation"]
    _run([*pip, "-w", str(tmp_path / "dist"), "."], source, env)
    assert len(list((tmp_path / "dist").glob("mrta_rl-*.whl"))) == 1
    left = sorted(set(files_below(source)) - set(before))
    assert not left, f"left in the sources: {[str(p) for p in left[:5]]}"


@pytest.fixture(scope="module")
def wheel_env(tmp_path_factory):
    """``(wheel, venv bin dir, subprocess env, work dir outside the repository)``."""
    work = tmp_path_factory.mktemp("wheel")
    assert not work.resolve().is_relative_to(ROOT)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    copy_sources(work / "source")
    pip = [sys.executable, "-m", "pip"]
    _run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", "dist", "./source"], work, env)
    (wheel,) = (work / "dist").glob("mrta_rl-*.whl")
    venv = work / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], work, env)
    purelib = subprocess.run(
        [
            venv / "bin" / "python",
            "-c",
            "import sysconfig; print(sysconfig.get_paths()['purelib'])",
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    # the test environment's packages (torch, torchrl, hydra...) after the venv's own; the test
    # environment's own .pth files (its editable install of the repository) are not read
    tested = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(purelib) / "test_env.pth").write_text("\n".join(sorted(tested)) + "\n")
    _run(
        [*pip, "--python", str(venv / "bin" / "python"), "install", "--no-deps", "--no-index"]
        + [str(wheel)],
        work,
        env,
    )
    home = work / "home"  # a directory of the user's: outside the repository and the venv
    home.mkdir()
    return wheel, venv / "bin", env, home


def test_wheel_ships_every_package_and_config(wheel_env):
    wheel = wheel_env[0]
    names = set(zipfile.ZipFile(wheel).namelist())
    # every folder of modules, with or without an __init__.py (a folder without one is not shipped)
    packages = {
        str(p.parent.relative_to(ROOT))
        for p in (ROOT / "mrta_rl").rglob("*.py")
        if "__pycache__" not in p.parts
    } | {"mrta_rl/conf"}
    shipped = {str(Path(n).parent) for n in names if n.endswith("/__init__.py")}
    assert packages <= shipped, f"not in the wheel (pyproject.toml packages): {packages - shipped}"
    configs = {
        f"mrta_rl/conf/{p.relative_to(ROOT / 'conf')}" for p in (ROOT / "conf").rglob("*.yaml")
    }
    assert configs and configs <= names, f"configs not in the wheel: {configs - names}"


def test_installed_wheel_runs_from_anywhere(wheel_env):
    _, bin_dir, env, home = wheel_env
    team = home / "my_team.yaml"
    team.write_text(TEAM)
    python = str(bin_dir / "python")
    for command in COMMANDS:
        assert (bin_dir / command).is_file(), command
    # both training runs and the env check at once: the three are independent processes
    trains = [
        subprocess.Popen(
            [str(bin_dir / "mrta-train"), "learner=greedy", "debug=smoke", *extra],
            cwd=home,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for extra in ([], [f"system={team}"])
    ]
    gym = _run([python, "-c", GYM_CHECK, str(team)], home, env).stdout.splitlines()
    for train in trains:
        out, err = train.communicate(timeout=300)
        assert train.returncode == 0, f"{train.args}:\n{out}\n{err}"
    assert Path(gym[0]).resolve().is_relative_to(bin_dir.parent.resolve())  # the wheel's copy
    assert [line.split()[:2] for line in gym[1:]] == [
        ["mrta_rl/Auction-System1-v0", "6"],
        ["mrta_rl/Auction-System2-v0", "10"],
        ["mrta_rl/Auction-v0", "3"],
    ]
    run_dirs = sorted((home / "outputs").glob("*/*"))  # Hydra's default, under the working dir
    systems = sorted(json.loads((d / "metrics.json").read_text())["system"] for d in run_dirs)
    assert systems == ["my_team", "system2"]
    report = _run([str(bin_dir / "mrta-report"), *map(str, run_dirs)], home, env)
    assert "2 runs, 0 missing" in report.stdout
    (report_file,) = (home / "outputs").rglob("report.md")
    text = report_file.read_text()
    assert "my_team" in text and "system2" in text
