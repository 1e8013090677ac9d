"""Bad inputs refused up front by the scripts: one ``error:`` line naming the file, exit 2.

Oversized teams and hostile system files are refused before Hydra composes them or anything is
built, and leave no run dir (``mrta_rl/systems/files.py``, ``runners/validation.py``).
"""

from __future__ import annotations

import os

import pytest

from tests.smoke.test_cli import assert_user_error, train, write_system


def billion_laughs() -> str:
    lines = ['  a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for previous, name in zip("abcdefgh", "bcdefghi", strict=True):
        lines.append(f"  {name}: &{name} [" + ", ".join([f"*{previous}"] * 9) + "]")
    return "name: mine\nrobots: {R1: [T1]}\nlaughs:\n" + "\n".join(lines) + "\n"


def many_robots(size: int) -> str:
    rows = [f"  R{i}: [T1, T2, T3]" for i in range(size // 16)]  # >= 17 bytes a row
    return "name: mine\nrobots:\n" + "\n".join(rows) + "\n"


SYSTEM_FILES = {
    "billion_laughs": (billion_laughs(), "YAML aliases"),
    "nested_lists": ("name: mine\nrobots: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper"),
    "binary": (None, "not UTF-8"),
    "two_megabytes": (many_robots(2_000_000), "more than the limit of 1,048,576 bytes"),
}


@pytest.mark.parametrize("case", sorted(SYSTEM_FILES))
def test_hostile_system_file_is_refused_before_it_is_read(case, tmp_path):
    text, reason = SYSTEM_FILES[case]
    search = write_system(tmp_path, "")
    path = tmp_path / "search" / "system" / "mine.yaml"
    if text is None:
        path.write_bytes(b"\xc0\xff" + os.urandom(998))
    else:
        path.write_text(text)
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=greedy", "system=mine", search)
    assert_user_error(code, err, str(path), reason)
    assert err.count("\n") == 1
    assert not run_dir.exists()


@pytest.mark.parametrize("n_robots", [10_000_000, 100_000_000])
def test_huge_random_team_is_refused_before_it_is_drawn(n_robots, tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "system=random", f"system.n_robots={n_robots}")
    assert_user_error(code, err, "system random", f"{n_robots:,} robots x 20 task types", "limit")
    assert not run_dir.exists()


def test_team_of_a_thousand_robots_is_not_refused(tmp_path):
    run_dir = tmp_path / "run"
    code, out, err = train(
        run_dir, "learner=greedy", "system=random", "system.n_robots=1000", "eval.episodes=1"
    )
    assert code == 0, err
    assert (run_dir / "metrics.json").is_file()
