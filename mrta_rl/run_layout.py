"""The files of a run dir: their names, and one checked loader per file, refusals naming the key.

The names of a run dir's files are declared here once, for the runners that write them and the
reports that read them. A run dir is data that anyone may have edited, truncated or damaged. Its
files are read here, checked against what the code that wrote them writes (types, ranges, finite
numbers), and refused with a :class:`RunDirError` naming the file and the key, so that a damaged
file is never half-used and never ends in a traceback:

* ``training.json`` of a training checkpoint (:func:`read_training_state`): the training loop's
  ``loop`` block (``episode`` in ``[0, train.episodes]``, the counters of the learner's
  ``training_loop``, one curve row per episode played, what the run has ``spent`` so far) and
  the learner's ``checkpoint_state`` (a mapping; the learner checks its content in
  ``restore_state``);
* ``metrics.json`` of a finished run (:func:`read_metrics`), as the reports read it;
* ``.hydra/config.yaml`` is read by :func:`~mrta_rl.runners.run_config.read_run_config`.

Every file is read through ``mrta_rl/checked_files.py`` (regular files only, bounded in bytes,
JSON without NaN), whose :class:`~mrta_rl.checked_files.RunDirError` every refusal is.
"""

from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path
from typing import Any

from mrta_rl.checked_files import RunDirError, read_json
from mrta_rl.config import short_list

# the files of a run dir, written by the runners and read by the runners and the reports
CONFIG_FILE = Path(".hydra") / "config.yaml"
HYDRA_FILE = Path(".hydra") / "hydra.yaml"
LEARNER_DIR = "learner"  # final learner state (Learner.save)
CHECKPOINT_DIR = "checkpoint"  # training checkpoints: version folders and the pointer file
POINTER_FILE = "latest"  # in CHECKPOINT_DIR: the name of the current version folder
METRICS_FILE = "metrics.json"
EVAL_METRICS_FILE = "eval_metrics.json"  # a re-evaluation (scripts/evaluate.py) beside metrics.json
REFUSED_FILE = "refused.json"  # instead of metrics.json: the run was refused up front, and why
TEAM_FILE = "team.json"  # in a learner state folder: the team it was trained on (save_learner)
STATE_FILE = "training.json"  # loop counters, curve so far, learner checkpoint_state
REFUSED_JOBS_FILE = "refused_jobs.jsonl"  # in a sweep dir: the jobs refused before they started


def write_json(path: Path, payload: dict[str, Any], *, exclusive: bool = False) -> None:
    """Write JSON atomically (temporary file then rename), so a file is never half-written.

    Args:
        path: The file.
        payload: JSON-serialisable content (no NaN).
        exclusive: Never replace an existing file (the rename is a hard link that fails if
            ``path`` exists): the results of a run are never overwritten by another run.

    Raises:
        RunDirError: if ``exclusive`` and ``path`` exists.
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n")
    except BaseException:  # a disk full or a file size limit leaves no half-written file
        tmp.unlink(missing_ok=True)
        raise
    if not exclusive:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise RunDirError(
            f"{path} was written by another run meanwhile; this run's results are kept in {tmp}"
        ) from None
    tmp.unlink()


CURVE_ROW = ("env_ticks", "episode", "team_return_mean")  # metrics.CURVE_COLUMNS
# a checkpoint's loop.spent: what the run spent up to it, in every process of its life, so that a
# resumed run adds it (runners/checkpoint.py LoopTime, metrics/usage.py RunResources); each >= 0
SPENT = (
    *("wall_s", "collect_s", "train_s"),  # the training loop's wall time, collection, updates
    *("run_wall_s", "cpu_s", "peak_rss_mb"),  # the run's wall time, CPU time, peak memory
)
# metrics.json as train() writes it (EpisodeSummary.to_json): "*" = any key; a key ending in
# "?" may be absent; INT, NUMBER (finite), OPTIONAL (finite or null), STR, ANY are leaves
INT, NUMBER, OPTIONAL, STR, ANY = "int", "number", "number or null", "string", "any"
SUMMARY = {
    "episodes": INT,
    "team_return": {"mean": OPTIONAL, "std": OPTIONAL, "per_episode?": [OPTIONAL]},
    "ctr": {"*": {"L": OPTIONAL, "H": OPTIONAL}},
    "ctr_overall": {"L": OPTIONAL, "H": OPTIONAL},
    "itr": {"*": OPTIONAL},
    "return_by_type?": {"*": OPTIONAL},  # absent from runs made before it existed
    "return_by_group?": {"*": {"types": [STR], "return": NUMBER}},
    "split?": STR,  # eval.split played
    # a planner's decision time in evaluation (Learner.decision_time: ms_per_tick, total_s...)
    "decision_time?": {"*": NUMBER},
}
LEARNER = {"name": STR, "label": STR, "kind": STR}  # runners/train.py learner_record
# the Ray workers of a run (cluster/workers.py RayWorkers.summary): a record, not read as numbers
WORKERS = {"count": INT, "address": STR, "nodes": INT, "*": ANY}
METRICS = {
    "learner": LEARNER,
    "system": STR,
    "seed": INT,
    "eval": SUMMARY,
    "baseline_greedy": SUMMARY,
    "train?": {"workers?": WORKERS, "*": NUMBER},
    "learning_space?": {"*": INT},
    # metrics/usage.py RunResources.to_json: wall_s, cpu_s, peak_rss_mb and peak_rss_scope
    "resources?": {"peak_rss_scope?": STR, "*": NUMBER},
    "*": ANY,  # other blocks (checkpoint) are not read as numbers
}


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _refuse(path: Path, key: str, what: str, value: Any) -> RunDirError:
    shown = repr(value)
    return RunDirError(f"{path}: {key}: must be {what}, got {shown[:80]}")


def check_loop(loop: Any, path: Path, counters: tuple[str, ...], episodes: int) -> dict[str, Any]:
    """Check the ``loop`` block of a ``training.json``.

    Args:
        loop: The block.
        path: The file, for messages.
        counters: The counters the learner's training loop keeps (its module's ``COUNTERS``).
        episodes: The run's ``train.episodes`` (the most episodes a checkpoint can follow).

    Returns:
        The block.

    Raises:
        RunDirError: naming the file and the key at fault.
    """
    if not isinstance(loop, dict):
        raise _refuse(path, "loop", "a mapping", loop)
    episode = loop.get("episode")
    if not _is_int(episode) or not 0 <= episode <= episodes:
        raise _refuse(
            path, "loop.episode", f"an integer in [0, {episodes}] (train.episodes)", episode
        )
    for key in counters:
        if not _is_int(loop.get(key)) or loop[key] < 0:
            raise _refuse(path, f"loop.{key}", "an integer >= 0", loop.get(key, "nothing"))
    spent = loop.get("spent", {})  # absent from checkpoints written before it existed: none
    if not isinstance(spent, dict):
        raise _refuse(path, "loop.spent", "a mapping", spent)
    for key, value in spent.items():
        if key not in SPENT:
            raise RunDirError(f"{path}: loop.spent.{key}: unknown key (known: {', '.join(SPENT)})")
        if not _is_number(value) or value < 0:
            raise _refuse(path, f"loop.spent.{key}", "a finite number >= 0", value)
    curve = loop.get("curve")
    if not isinstance(curve, list) or len(curve) != episode:
        raise _refuse(
            path, "loop.curve", f"a list of {episode} rows (one per episode played)", curve
        )
    for i, row in enumerate(curve):
        where = f"loop.curve[{i}]"
        if not isinstance(row, dict) or set(row) != set(CURVE_ROW):
            raise _refuse(path, where, f"a row of {', '.join(CURVE_ROW)}", row)
        if row["episode"] != i + 1 or not _is_int(row["episode"]):
            raise _refuse(path, f"{where}.episode", f"episode {i + 1}", row["episode"])
        if not _is_int(row["env_ticks"]) or row["env_ticks"] < 0:
            raise _refuse(path, f"{where}.env_ticks", "an integer >= 0", row["env_ticks"])
        if not _is_number(row["team_return_mean"]):
            raise _refuse(
                path, f"{where}.team_return_mean", "a finite number", row["team_return_mean"]
            )
    return loop


def read_training_state(
    path: Path, counters: tuple[str, ...], episodes: int
) -> tuple[dict[str, Any], dict]:
    """Read and check a checkpoint's ``training.json``.

    Args:
        path: The file.
        counters: The counters of the learner's training loop (``COUNTERS`` of its module).
        episodes: The run's ``train.episodes``.

    Returns:
        ``(loop, learner_state)``: the checked loop block and the learner's checkpoint state (a
        mapping; the learner's ``restore_state`` checks its content).

    Raises:
        RunDirError: naming the file and the key at fault.
    """
    state = read_json(path)
    if not isinstance(state, dict):
        raise _refuse(path, "(top level)", "a mapping with loop and learner", state)
    for key in ("loop", "learner"):
        if key not in state:
            raise RunDirError(f"{path}: {key}: missing")
    if not isinstance(state["learner"], dict):
        raise _refuse(
            path, "learner", "a mapping (the learner's checkpoint state)", state["learner"]
        )
    return check_loop(state["loop"], path, counters, episodes), state["learner"]


def check_schema(value: Any, schema: Any, path: Path, key: str) -> None:
    """Check a JSON value against a schema of the form of :data:`METRICS`.

    Raises:
        RunDirError: naming the file and the first key at fault.
    """
    if schema == ANY:
        return
    if isinstance(schema, str):
        ok = {
            INT: _is_int,
            NUMBER: _is_number,
            OPTIONAL: lambda v: v is None or _is_number(v),
            STR: lambda v: isinstance(v, str),
        }[schema](value)
        if not ok:
            raise _refuse(path, key, f"a{'n' if schema == INT else ''} {schema}", value)
        return
    if isinstance(schema, list):
        if not isinstance(value, list):
            raise _refuse(path, key, "a list", value)
        for i, item in enumerate(value):
            check_schema(item, schema[0], path, f"{key}[{i}]")
        return
    if not isinstance(value, dict):
        raise _refuse(path, key, "a mapping", value)
    prefix = f"{key}." if key else ""
    for declared in schema:
        name = declared.rstrip("?")
        if name != "*" and name not in value and f"{name}?" not in schema:
            raise RunDirError(f"{path}: {prefix}{name}: missing")
    for name, item in value.items():
        sub = schema.get(name, schema.get(f"{name}?", schema.get("*")))
        if sub is None:
            raise RunDirError(f"{path}: {prefix}{name}: unknown key")
        check_schema(item, sub, path, f"{prefix}{name}")


def read_metrics(path: Path) -> dict[str, Any]:
    """Read and check a finished run's ``metrics.json`` (:data:`METRICS`).

    The learner's and the greedy baseline's blocks must name the same task types and robots.

    Args:
        path: The file.

    Returns:
        The content.

    Raises:
        RunDirError: naming the file and the key at fault.
    """
    metrics = read_json(path)
    check_schema(metrics, METRICS, path, "")
    learned, greedy = metrics["eval"], metrics["baseline_greedy"]
    for block in ("ctr", "itr", "return_by_type"):
        if set(learned.get(block, ())) != set(greedy.get(block, ())):
            raise RunDirError(
                f"{path}: eval.{block}: names {short_list(sorted(learned.get(block, ())))}, but "
                f"baseline_greedy.{block} names {short_list(sorted(greedy.get(block, ())))}"
            )
    if learned["episodes"] < 1:
        raise _refuse(path, "eval.episodes", "an integer >= 1", learned["episodes"])
    return metrics
