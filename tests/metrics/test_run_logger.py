"""logger=csv|tensorboard|wandb|mlflow: every tracker gets the curve, the training scalars and
the final metrics, in files of the run dir and with no network."""

from __future__ import annotations

import csv
import json
import re
import struct
import time
from pathlib import Path

import pytest
from hydra.utils import instantiate

from mrta_rl.metrics.run_logger import final_scalars
from mrta_rl.runners import train

WANDB_BLOCK = 32768  # wandb's run file is a LevelDB log: 32 KiB blocks of chunked records


def curve(run_dir: Path) -> list[tuple[int, float]]:
    with (run_dir / "curve.csv").open() as f:
        return [(int(r["env_ticks"]), float(r["team_return_mean"])) for r in csv.DictReader(f)]


def wandb_records(path: Path) -> tuple[list[dict], dict]:
    """History rows and the final summary of an offline wandb run file."""
    from wandb.proto import wandb_internal_pb2

    raw = path.read_bytes()
    assert raw[:4] == b":W&B"
    pos, chunks, records = 7, b"", []
    while pos + 7 <= len(raw):
        left = WANDB_BLOCK - pos % WANDB_BLOCK
        _, length, kind = struct.unpack("<IHB", raw[pos : pos + 7])
        if left < 7 or (length == 0 and kind == 0):  # block trailer or padding
            pos += left
            continue
        chunks += raw[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):  # a full record, or the last chunk of one
            records.append(chunks)
            chunks = b""
    history, summary = [], {}
    for data in records:
        record = wandb_internal_pb2.Record()
        record.ParseFromString(data)
        kind = record.WhichOneof("record_type")
        if kind == "history":
            history.append({_key(i): json.loads(i.value_json) for i in record.history.item})
        elif kind == "summary":
            summary.update({_key(i): json.loads(i.value_json) for i in record.summary.update})
    return history, summary


def _key(item) -> str:
    return item.key or "/".join(item.nested_key)  # a key with "/" may come split


def mlflow_metric(run: Path, name: str) -> list[tuple[int, float]]:
    """``(step, value)`` of one metric in an MLflow file store run (lines: time value step)."""
    lines = (run / "metrics" / name).read_text().split("\n")
    return [(int(step), float(value)) for _, value, step in (ln.split() for ln in lines if ln)]


def test_wandb_offline(compose_cfg, tmp_path):
    cfg = compose_cfg(["learner=dql", "debug=smoke", "logger=wandb"])
    metrics = train(cfg, run_dir=tmp_path)
    (run_file,) = (tmp_path / "wandb").glob("offline-run-*/run-*.wandb")
    # wandb's own process writes the file: the last records can land just after finish() returns
    deadline = time.monotonic() + 120  # bounds the wait only
    history, summary = wandb_records(run_file)
    while "train/fps" not in summary and time.monotonic() < deadline:
        time.sleep(0.2)
        history, summary = wandb_records(run_file)
    logged = [
        (h["train/step"], h["train/team_return"]) for h in history if "train/team_return" in h
    ]
    assert logged == curve(tmp_path) and len(logged) == cfg.train.episodes
    assert [h["train/epsilon"] for h in history if "train/epsilon" in h]
    final = {k: v for h in history for k, v in h.items()}  # the last value of each key
    assert final["eval/team_return/mean"] == metrics["eval"]["team_return"]["mean"]
    assert (
        final["baseline_greedy/team_return/mean"]
        == (metrics["baseline_greedy"]["team_return"]["mean"])
    )
    assert final["train/fps"] == pytest.approx(
        metrics["train"]["env_ticks"] / metrics["train"]["wall_s"]
    )
    assert summary["train/team_return"] == logged[-1][1]  # W&B's run summary: the last curve point


def test_mlflow_file_store(compose_cfg, tmp_path):
    cfg = compose_cfg(["learner=vdn", "debug=smoke", "logger=mlflow"])
    metrics = train(cfg, run_dir=tmp_path)
    (run,) = [p.parent for p in (tmp_path / "mlruns").glob("*/*/meta.yaml")]
    assert mlflow_metric(run, "train/team_return") == curve(tmp_path)
    for name in ("train/loss", "train/epsilon", "fps/collection", "fps/training"):
        assert mlflow_metric(run, name), name  # the neural runner's scalars
    (final,) = mlflow_metric(run, "eval/team_return/mean")
    assert final == (metrics["train"]["env_ticks"], metrics["eval"]["team_return"]["mean"])


@pytest.mark.parametrize("logger", ["csv", "tensorboard"])
def test_csv_and_tensorboard(logger, compose_cfg, tmp_path):
    cfg = compose_cfg(["learner=dql", "debug=smoke", f"logger={logger}"])
    metrics = train(cfg, run_dir=tmp_path)
    assert len(curve(tmp_path)) == cfg.train.episodes
    if logger == "tensorboard":
        assert list((tmp_path / "tensorboard").rglob("events.out.tfevents.*"))
        return
    scalars = tmp_path / "torchrl" / "train" / "scalars"
    with (scalars / "train" / "team_return.csv").open() as f:
        assert [(int(s), float(v)) for s, v in csv.reader(f)] == curve(tmp_path)
    step, value = (scalars / "eval" / "team_return" / "mean.csv").read_text().split(",")
    assert float(value) == metrics["eval"]["team_return"]["mean"]


def test_a_run_left_open_does_not_block_the_next(compose_cfg, tmp_path):
    """W&B and MLflow keep one active run per process: an unfinished one is ended first."""
    cfg = compose_cfg(["learner=greedy", "debug=smoke", "logger=mlflow"])
    hydra_logger = instantiate(cfg.logger)
    hydra_logger(run_dir=tmp_path / "left_open").close()  # as a loop that failed leaves it
    train(cfg, run_dir=tmp_path / "next")
    for name in ("left_open", "next"):
        (meta,) = (tmp_path / name / "mlruns").glob("*/*/meta.yaml")
        assert "status: 3" in meta.read_text(), name  # MLflow's RunStatus.FINISHED
        assert (meta.parent / "tags" / "mlflow.runName").read_text() == name  # the run dir's


def test_the_loggers_page_names_keys_the_tracker_receives(compose_cfg, tmp_path):
    """Every final-metric key docs/guide/loggers.md names is a scalar of the tracker's run."""
    page = (Path(__file__).resolve().parents[2] / "docs" / "guide" / "loggers.md").read_text()
    named = set(re.findall(r"`((?:eval|baseline_greedy)/[\w/]+)`", page))
    assert named, "the page names the final metrics' keys"
    cfg = compose_cfg(["learner=greedy", "system=system1", "debug=smoke", "logger=csv"])
    train(cfg, run_dir=tmp_path)
    scalars = tmp_path / "torchrl" / "train" / "scalars"
    logged = {str(p.relative_to(scalars).with_suffix("")) for p in scalars.rglob("*.csv")}
    assert sorted(named - logged) == []


def test_a_tracker_is_not_given_a_scalar_per_robot_of_a_large_team():
    """A tracker opens a file or a series per scalar: 100,000 robots' ITR ran out of files."""
    small = {"eval": {"team_return": {"mean": 5.0}, "itr": {f"R{i}": 1.0 for i in range(3)}}}
    large = {"eval": {"team_return": {"mean": 5.0}, "itr": {f"R{i}": 1.0 for i in range(257)}}}
    assert final_scalars(small) == {
        "eval/team_return/mean": 5.0,
        "eval/itr/R0": 1.0,
        "eval/itr/R1": 1.0,
        "eval/itr/R2": 1.0,
    }
    assert final_scalars(large) == {"eval/team_return/mean": 5.0}
