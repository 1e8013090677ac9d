"""Learner throughput benchmark: training copy-ticks/s next to the env and a plain loop.

For each learner that trains (:func:`trained_learners`: the ``learner/`` yaml files of the
config search path, the shipped ``conf/`` and any ``--config-dir``, whose class has a training
loop) the benchmark composes the default run config (``conf/config.yaml``, so ``train.batch_size``
and the learner's own defaults), builds the run as ``scripts/train.py`` does and times the
training loop its class declares over a short fixed budget of ``episodes`` episodes. In the same
process it times two yardsticks:

* the bare env at the same batch size under the greedy policy (``bench/env.py``);
* a plain per-copy Python loop of the dynamics, ``mrta_rl/envs/reference.py`` (the spec
  read as one copy with tasks in a list) under greedy.

Absolute figures on a shared machine are noisy; the ratios to the yardsticks measured in the same
process are what to compare. The measurements run in a worker process (:func:`measure`) whose
``mrta_rl`` can come from another checkout (``PYTHONPATH``), so that today's code and a branch are
measured side by side, in turns, with this same module (:func:`run_worker`).
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

# runners/torch_loop.py's info; labels_per_s: a teaching learner's (expert_iteration's planner)
NEURAL_RATES = ("fps_collection", "fps_training", "labels_per_s", "gradient_steps")
RATES = NEURAL_RATES[:3]  # the rates of the table, min and median
WARMUP_OVERRIDES = ("env.horizon=20", "train.episodes=1")  # loads compiled code, fills caches
# the budgets' validation evaluations (conf/budget/) are not training: the benchmark times training
TRAINING_ONLY = ("train.validate_every=0", "train.keep_best=false")
TEAM_KEYS = ("system.", "env.")  # overrides that also set the yardsticks' team and dynamics


def _repo_root() -> Path:
    import mrta_rl

    return Path(mrta_rl.__file__).resolve().parents[1]


def trained_learners(config_dirs: Sequence[str | os.PathLike] = ()) -> list[str]:
    """The learners of the config search path that train (a fixed policy has nothing to time).

    Args:
        config_dirs: User config dirs after the shipped ``conf/`` (``--config-dir``).

    Returns:
        Their names, sorted.
    """
    from mrta_rl.learners.registry import learner_files, learner_named

    return [
        name for name in learner_files(config_dirs) if learner_named(name, config_dirs).trains()
    ]


def search_path(config_dirs: Sequence[str | os.PathLike]) -> list[str]:
    """The Hydra override that adds the user config dirs to the search path (none: [])."""
    if not config_dirs:
        return []
    dirs = ",".join(f"file://{Path(d).resolve()}" for d in config_dirs)
    return [f"hydra.searchpath=[{dirs}]"]


def _compose(overrides: list[str]) -> Any:
    """The run config of ``scripts/train.py`` with overrides (Hydra compose API)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    # a checkout's own conf/ first: a --baseline checkout may predate mrta_rl.conf_paths
    config_dir = _repo_root() / "conf"
    if not (config_dir / "config.yaml").is_file():
        from mrta_rl.conf_paths import conf_dir

        config_dir = conf_dir()
    with initialize_config_dir(config_dir=str(config_dir), version_base=None):
        return compose(config_name="config", overrides=overrides)


def train_once(
    name: str, system: str, overrides: list[str]
) -> tuple[int, float, float, int, dict[str, Any]]:
    """Build the run of ``learner=name`` and time its training loop.

    Returns:
        (copy-ticks, wall s, CPU s of the process, batch, the loop's info: neural runs add
        ``fps_collection`` and ``fps_training``).
    """
    from mrta_rl.runners.train import build_run, training_loop

    cfg = _compose([f"learner={name}", f"system={system}", "train.progress_bar=false", *overrides])
    run = build_run(cfg, name)
    cls = type(run.learner)
    # a --baseline older than the learners' own training_loop looks it up by kind
    loop = training_loop(cls if isinstance(getattr(cls, "training_loop", None), str) else cls.kind)
    with tempfile.TemporaryDirectory() as run_dir:
        start, cpu = time.perf_counter(), time.process_time()
        info = loop(run, cfg, Path(run_dir))
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    return int(info["env_ticks"]), wall, cpu, int(run.env.batch_size), info


def measure(
    learners: list[str],
    system: str,
    episodes: int,
    seconds: float,
    horizon: int = 0,
    experiment: str = "",
    config_dirs: Sequence[str] = (),
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """One worker's measurements: the two yardsticks and every learner's training speed.

    Args:
        learners: Learner names (``learner/`` yaml files of the config search path).
        system: ``conf/system`` name.
        episodes: Training episodes per learner (the fixed short budget).
        seconds: Least wall time of each yardstick.
        horizon: Ticks per training episode (0: the config's, ``env.horizon``).
        experiment: ``conf/experiment`` file applied to every learner run ("" for none).
        config_dirs: User config dirs added to the search path (``--config-dir``).
        overrides: Config overrides of every learner run (``learner.network=set``); the
            ``system.*`` and ``env.*`` ones also set the yardsticks' team.

    Returns:
        ``{"plain": ticks/s, "env": {batch: ticks/s}, "learners": {name: {...}}}``.
    """
    try:
        from mrta_rl.bench import env as benchmark
    except ImportError:  # a --baseline from before the benchmarks moved to mrta_rl/bench
        from mrta_rl.envs import benchmark  # type: ignore[no-redef]
    from mrta_rl.systems import build_system

    cfg = _compose([f"system={system}", *(o for o in overrides if o.startswith(TEAM_KEYS))])
    from omegaconf import OmegaConf

    built = build_system(OmegaConf.to_container(cfg.system, resolve=True))
    # a checkout older than bench_plain_loop (a --baseline) borrows this code's plain loop
    plain_loop = getattr(benchmark, "bench_plain_loop", None)
    plain = plain_loop(built, min_seconds=seconds).ticks_per_s if plain_loop else None
    out: dict[str, Any] = {"plain": plain, "env": {}}
    out["learners"] = {}
    for name in learners:
        warm_start = time.perf_counter()
        pinned = [f"experiment={experiment}"] if experiment else []
        pinned += [*search_path(config_dirs), *TRAINING_ONLY, *overrides]
        train_once(name, system, [*pinned, *WARMUP_OVERRIDES])
        warmup = time.perf_counter() - warm_start
        budget = [*pinned, f"train.episodes={episodes}"]
        budget += [f"env.horizon={horizon}"] if horizon else []
        ticks, wall, cpu, batch, info = train_once(name, system, budget)
        if str(batch) not in out["env"]:  # JSON keys are strings
            bare = benchmark.bench_env(built, batch, min_seconds=seconds)
            out["env"][str(batch)] = bare.ticks_per_s
        out["learners"][name] = {
            "ticks": ticks,
            "wall_s": wall,
            "ticks_per_s": ticks / wall,
            # CPU time of the process: on a shared machine, less moved by the other processes
            "cpu_ticks_per_s": ticks / cpu,
            "batch_size": batch,
            "warmup_s": warmup,
            # neural learners: collection frames/s and training replayed transitions/s apart
            **{key: info[key] for key in NEURAL_RATES if key in info},
        }
        logger.info("%s: %.0f copy-ticks/s", name, ticks / wall)
    return out


def learners_in(
    root: Path, learners: list[str], config_dirs: Sequence[str | os.PathLike] = ()
) -> list[str]:
    """The learners that the checkout ``root`` has (``conf/learner/<name>.yaml``), in order.

    A ``--baseline`` older than a learner measures the others; the table shows no speed-up for
    the learner it lacks. A learner of a user config dir counts for every checkout.
    """
    folders = [root / "conf", *(Path(d) for d in config_dirs)]
    return [
        name
        for name in learners
        if any((folder / "learner" / f"{name}.yaml").is_file() for folder in folders)
    ]


def run_worker(
    code_root: Path | None,
    learners: list[str],
    system: str,
    episodes: int,
    seconds: float,
    horizon: int = 0,
    experiment: str = "",
    config_dirs: Sequence[str | os.PathLike] = (),
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """Run :func:`measure` in a fresh process importing ``mrta_rl`` from ``code_root``.

    Args:
        code_root: Checkout whose ``mrta_rl`` is measured (None: this one).
        learners: Learner names (``learner/`` yaml files of the config search path).
        system: ``conf/system`` name.
        episodes: Training episodes per learner.
        seconds: Least wall time of each yardstick.
        horizon: Ticks per training episode (0: the config's).
        experiment: ``conf/experiment`` file applied to every learner run ("" for none).
        config_dirs: User config dirs added to the search path (``--config-dir``).
        overrides: Config overrides of every run (:func:`measure`).

    Returns:
        The worker's :func:`measure` output.

    Raises:
        RuntimeError: if the worker fails (its stderr tail is in the message).
    """
    root = Path(code_root) if code_root is not None else _repo_root()
    env = dict(os.environ, PYTHONPATH=str(root))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.json"
        # -c keeps this module's folder off sys.path (it holds a torchrl.py)
        dirs = os.pathsep.join(str(Path(d).resolve()) for d in config_dirs) or "-"
        argv = [str(out), system, str(episodes), str(seconds), str(horizon), experiment or "-"]
        argv += [dirs, json.dumps(list(overrides)), *learners_in(root, learners, config_dirs)]
        code = f"import runpy, sys; sys.argv = ['bench', *{argv!r}]; "
        code += f"runpy.run_path({str(Path(__file__).resolve())!r}, run_name='__main__')"
        args = [sys.executable, "-c", code]
        done = subprocess.run(args, env=env, cwd=root, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"bench worker on {root} failed:\n{done.stderr[-3000:]}")
        return json.loads(out.read_text())


def summarize(runs: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Rows per (code, learner): min and median over repeats of ticks/s and the ratios.

    Args:
        runs: Code label -> the repeats' :func:`measure` outputs.

    Returns:
        One dict per code and learner (JSON-ready).
    """
    rows = []
    # the plain loop of each repeat, from the first code that measured it
    plains = [
        next(reps[i]["plain"] for reps in runs.values() if reps[i]["plain"])
        for i in range(min(len(reps) for reps in runs.values()))
    ]
    for code, repeats in runs.items():
        for name in repeats[0]["learners"]:
            speed = [r["learners"][name]["ticks_per_s"] for r in repeats]
            cpu_speed = [r["learners"][name]["cpu_ticks_per_s"] for r in repeats]
            batch = repeats[0]["learners"][name]["batch_size"]
            vs_env = [r["learners"][name]["ticks_per_s"] / r["env"][str(batch)] for r in repeats]
            vs_plain = [
                r["learners"][name]["ticks_per_s"] / plain
                for r, plain in zip(repeats, plains, strict=False)
            ]
            # the learner's own time per tick: the run's, less the bare env's at the same B
            own_us = [
                batch * 1e6 * (1 / r["learners"][name]["ticks_per_s"] - 1 / r["env"][str(batch)])
                for r in repeats
            ]
            rows.append(
                {
                    "code": code,
                    "learner": name,
                    "batch_size": batch,
                    "repeats": len(repeats),
                    "ticks_per_s_min": min(speed),
                    "ticks_per_s_median": statistics.median(speed),
                    "cpu_ticks_per_s_min": min(cpu_speed),
                    "cpu_ticks_per_s_median": statistics.median(cpu_speed),
                    "vs_env_median": statistics.median(vs_env),
                    "vs_plain_min": min(vs_plain),
                    "vs_plain_median": statistics.median(vs_plain),
                    "learner_us_per_tick_median": statistics.median(own_us),
                    "plain_ticks_per_s_median": statistics.median(plains),
                    **_rates(r["learners"][name] for r in repeats),
                }
            )
    return rows


def _rates(repeats: Any) -> dict[str, float]:
    """Min and median of the neural runs' collection and training rates (empty if tabular)."""
    runs = list(repeats)
    out: dict[str, float] = {}
    for key in RATES:
        values = [run[key] for run in runs if key in run]
        if values:
            out[f"{key}_min"], out[f"{key}_median"] = min(values), statistics.median(values)
    return out


def format_neural_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of the neural rows: collection, training and teaching rates apart.

    Collection counts copy-ticks per second spent in the Collector; training counts replayed
    transitions per second spent in gradient steps (``runners/torch_loop.py``); teacher labels
    count the copy-ticks a teaching learner's planner labels per second it spends labelling
    (``expert_iteration``; "-" for the others). Speed-ups are medians over the first code
    label's.
    """
    rows = [r for r in rows if "fps_collection_median" in r]
    if not rows:
        return ""
    codes = list(dict.fromkeys(r["code"] for r in rows))
    base = {r["learner"]: r for r in rows if r["code"] == codes[0]}
    lines = [
        "| learner | code | B | collection frames/s min | median | speed-up | "
        "training transitions/s min | median | speed-up | teacher labels/s min | median |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in sorted(rows, key=lambda r: (r["learner"], codes.index(r["code"]))):
        ref = base.get(r["learner"], {})
        cells = []
        for key in RATES:
            if f"{key}_median" not in r:
                cells.append("- | -" if key == "labels_per_s" else "- | - | -")
                continue
            cells.append(f"{r[f'{key}_min']:,.0f} | {r[f'{key}_median']:,.0f}")
            if key != "labels_per_s":  # a speed-up of the medians, "-" without a baseline
                old = ref.get(f"{key}_median")
                cells[-1] += f" | {r[f'{key}_median'] / old:.1f}x" if old else " | -"
        lines.append(f"| {r['learner']} | {r['code']} | {r['batch_size']} | {' | '.join(cells)} |")
    return "\n".join(lines)


def format_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of :func:`summarize` rows, with the speed-up over the first code label.

    The speed-up compares the mins and the medians of the two codes' copy-ticks/s, in wall time
    and in CPU time of the process (less moved by other processes on a shared machine).
    """
    codes = list(dict.fromkeys(r["code"] for r in rows))
    base = {r["learner"]: r for r in rows if r["code"] == codes[0]}
    lines = [
        "| learner | code | B | copy-ticks/s min | median | x env (same B) | x plain loop "
        "(min / median) | speed-up vs " + codes[0] + " (min / median) | "
        "CPU-time speed-up (min / median) | learner us/tick (run - env) |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in sorted(rows, key=lambda r: (r["learner"], codes.index(r["code"]))):
        b = base.get(r["learner"])
        keys = (
            "ticks_per_s_min",
            "ticks_per_s_median",
            "cpu_ticks_per_s_min",
            "cpu_ticks_per_s_median",
        )
        # "-": the first code did not measure this learner (a baseline older than it)
        up = [f"{r[k] / b[k]:.1f}x" if b else "-" for k in keys]
        lines.append(
            f"| {r['learner']} | {r['code']} | {r['batch_size']} | {r['ticks_per_s_min']:,.0f} | "
            f"{r['ticks_per_s_median']:,.0f} | {r['vs_env_median']:.2f} | "
            f"{r['vs_plain_min']:.2f} / {r['vs_plain_median']:.2f} | "
            f"{up[0]} / {up[1]} | {up[2]} / {up[3]} | "
            f"{r['learner_us_per_tick_median']:,.0f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":  # worker: out system episodes seconds horizon experiment dirs overrides
    worker_args = sys.argv[1:]
    out_path, system_name, n_episodes, min_s, n_ticks, pinned, dir_list, extra, *names = worker_args
    logging.basicConfig(level=logging.WARNING)
    experiment_name = "" if pinned == "-" else pinned
    user_dirs = [] if dir_list == "-" else dir_list.split(os.pathsep)
    result = measure(
        names,
        system_name,
        int(n_episodes),
        float(min_s),
        int(n_ticks),
        experiment_name,
        user_dirs,
        json.loads(extra),
    )
    Path(out_path).write_text(json.dumps(result, indent=2))
