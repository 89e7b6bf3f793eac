"""Work over worker processes (``codecsplat_warp.eval.shards``): the workers' devices, the round-robin split,
``run_sharded`` on two CPU processes (results in shard order, equal to running in this process; a worker's error
named by its shard, typed). The tasks are module-level so that the spawned workers can import them."""

from __future__ import annotations

import json
import os

import pytest
import torch

from codecsplat_warp.errors import DataError, InputError, ShardError
from codecsplat_warp.eval import shards
from codecsplat_warp.eval.evaluate import EvalConfig
from codecsplat_warp.eval.shards import report_progress, run_sharded, shard_devices, split_round_robin

CPU = torch.device("cpu")


def test_split_round_robin_deals_items_in_order():
    assert split_round_robin(list(range(7)), 3) == [[0, 3, 6], [1, 4], [2, 5]]
    assert split_round_robin(["a", "b"], 3) == [["a"], ["b"], []]
    assert split_round_robin([], 1) == [[]]
    for bad in (0, -1, True, 1.5):
        with pytest.raises(InputError, match="part count"):
            split_round_robin([1], bad)


def test_shard_devices_one_per_gpu_or_as_many_as_asked(monkeypatch):
    assert shard_devices("cpu", None) == [CPU] and shard_devices("cpu", 3) == [CPU] * 3
    for bad in (0, -2, True):
        with pytest.raises(InputError, match="worker count"):
            shard_devices("cpu", bad)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    gpu = [torch.device("cuda", i) for i in range(2)]
    assert shard_devices("auto", None) == gpu and shard_devices("cuda", None) == gpu
    assert shard_devices("cuda", 3) == [gpu[0], gpu[1], gpu[0]]  # round robin: two processes on the first GPU
    assert shard_devices("cuda:1", None) == [gpu[1]] and shard_devices("cuda:1", 2) == [gpu[1]] * 2
    with pytest.raises(InputError, match="sees 2 GPU"):
        shard_devices("cuda:2", None)


def _sum_of_squares(shard: list[int], device: torch.device) -> tuple:
    """A task: the sum of squares of ``shard`` on ``device``, with the process and its CPU thread count."""
    values = torch.tensor(shard, dtype=torch.float64, device=device)
    for done in range(len(shard) + 1):
        report_progress(done, len(shard))
    return float((values**2).sum()), str(device), os.getpid(), torch.get_num_threads()


def test_run_sharded_returns_the_results_in_shard_order():
    parts = split_round_robin(list(range(9)), 2)
    results = run_sharded(_sum_of_squares, parts, [CPU, CPU], progress=False)
    assert [r[:2] for r in results] == [_sum_of_squares(part, CPU)[:2] for part in parts] == [(120.0, "cpu"),
                                                                                              (84.0, "cpu")]
    assert len({r[2] for r in results} | {os.getpid()}) == 3  # two processes of their own
    assert all(r[3] == max(1, shards.available_cores() // 2) for r in results)  # the cores shared out
    alone = run_sharded(_sum_of_squares, [[3]], [CPU], progress=False)  # one shard: in this process
    assert alone == [(9.0, "cpu", os.getpid(), torch.get_num_threads())]
    with pytest.raises(InputError, match="one device per shard"):
        run_sharded(_sum_of_squares, parts, [CPU], progress=False)


def _fail_on_shard_one(shard: str, device: torch.device) -> str:
    """A task that raises what ``shard`` names (``ok``: no error)."""
    if shard == "data":
        raise DataError("scene x is corrupt")
    if shard == "value":
        raise ValueError("a bug")
    if shard == "exit":
        os._exit(3)
    return shard


@pytest.mark.parametrize("failure,error,match", [
    ("data", DataError, r"^shard 1 on cpu: scene x is corrupt$"),  # the package's errors keep their type
    ("value", ShardError, r"^shard 1 on cpu failed: ValueError: a bug\nthe worker's traceback:\nTraceback"),
    ("exit", ShardError, r"^shard 1 on cpu: its worker process exited with code 3 without a result$")])
def test_a_failing_worker_raises_an_error_naming_its_shard(failure, error, match):
    with pytest.raises(error, match=match) as raised:
        run_sharded(_fail_on_shard_one, ["ok", failure], [CPU, CPU], progress=False)
    if failure == "data":
        assert isinstance(raised.value.__cause__, ShardError) and "_fail_on_shard_one" in str(raised.value.__cause__)


def test_a_run_split_another_way_is_not_resumed(tmp_path):
    shard = tmp_path / "shards" / "0"
    shard.mkdir(parents=True)
    (shard / "results.json").write_text(json.dumps({"config": {"scenes": ["a", "c"]}}))
    configs = [EvalConfig(data="x", out=str(tmp_path / "shards" / str(k)), scenes=s)
               for k, s in enumerate([("a", "b"), ("c",)])]
    with pytest.raises(DataError, match="split over another number of workers"):
        shards._check_split(tmp_path, configs)
    shards._check_split(tmp_path, [EvalConfig(data="x", out=str(shard), scenes=("a", "c"))])

