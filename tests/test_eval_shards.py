"""Work over worker processes (``codecsplat_warp.eval.shards``): the workers' devices, the round-robin split,
``run_sharded`` on two CPU processes (results in shard order, equal to running in this process; a worker's error
named by its shard, typed), what ``codecsplat eval`` deals (whole scenes, or with RDO rows each scene's base rows
and RDO row groups), and ``codecsplat eval --workers 2|3 --device cpu`` writing the results.json of a one-process
run. The tasks are module-level so that the spawned workers can import them."""

from __future__ import annotations

import json
import os
import platform
from dataclasses import replace

import pytest
import torch

from codecsplat_warp.cli import main
from codecsplat_warp.device import freed_memory_kept, keep_freed_memory
from codecsplat_warp.errors import DataError, InputError, ShardError
from codecsplat_warp.eval import shards
from codecsplat_warp.eval.evaluate import EvalConfig, Evaluator, check_config
from codecsplat_warp.eval.shards import (format_worker_seconds, report_progress, run_sharded, shard_devices,
                                         split_round_robin, worker_seconds)
from codecsplat_warp.metrics import WEIGHTS_ENV
from codecsplat_warp.model.pretrained import save_pretrained
from conftest import tiny_coding_model
from test_cli_commands import write_scene

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


def _freed_memory_kept(shard: list[int], device: torch.device) -> bool:
    """A task: whether its process keeps the memory it frees."""
    return freed_memory_kept()


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="keeping freed memory needs glibc's mallopt")
def test_workers_keep_freed_memory_when_the_parent_does():
    assert keep_freed_memory()
    assert run_sharded(_freed_memory_kept, [[1], [2]], [CPU, CPU], progress=False) == [True, True]


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
    with pytest.raises(DataError, match="other scenes or units"):  # the same scenes, dealt as row groups
        shards._check_split(tmp_path, [EvalConfig(data="x", out=str(shard), scenes=("a", "c"), rdo_steps=(2,),
                                                  units=(("a", "base"), ("c", "2 steps λ=64")))])


def test_with_rdo_rows_the_base_rows_and_each_rdo_group_of_a_scene_are_dealt_apart_by_cost():
    config = EvalConfig(data="x", out="o", lambdas=(64.0, 256.0), baselines=(), rdo_steps=(2,))
    assert shards._group_costs(config) == {"base": 4 * shards.BASE_ROW_STEPS, "2 steps λ=64": 2.0,
                                           "2 steps λ=256": 2.0}
    split = shards._split(config, ["a", "c"], 3)
    assert [shard.units for shard in split] == [(("a", "base"),), (("c", "base"),),
                                                (("a", "2 steps λ=64"), ("a", "2 steps λ=256"),
                                                 ("c", "2 steps λ=64"), ("c", "2 steps λ=256"))]
    assert [shard.scenes for shard in split] == [("a",), ("c",), ("a", "c")] and split[2].out == "o/shards/2"
    assert len(shards._split(config, ["a", "c"], 8)) == 6  # no more workers than units
    for whole in (replace(config, rdo_steps=()), replace(config, renders=True)):  # whole scenes, as many as asked
        assert [(s.scenes, s.units) for s in shards._split(whole, ["a", "b", "c"], 2)] == [(("a", "c"), ()),
                                                                                        (("b",), ())]
    with pytest.raises(InputError, match="unknown row groups 2 steps λ=16; this evaluation's are base, 2 steps"):
        check_config(replace(config, units=(("a", "2 steps λ=16"),)))


def test_dealing_by_cost_balances_the_workers():
    # ten held-out scenes at one lambda: slow (21 s), medium (5.5 s) and base (3 s) units over four workers
    units = [(scene, group) for scene in range(10) for group in ("slow", "medium", "base")]
    cost = {"slow": 21.0, "medium": 5.5, "base": 3.0}
    hands = shards.deal_by_cost(units, [cost[g] for _, g in units], 4)
    assert sorted(u for hand in hands for u in hand) == sorted(units)
    assert all([units.index(u) for u in hand] == sorted(units.index(u) for u in hand) for hand in hands)
    loads = [sum(cost[g] for _, g in hand) for hand in hands]
    assert max(loads) - min(loads) <= cost["slow"] and max(loads) < 80.0  # like cards, the busiest would hold 80
    assert shards.deal_by_cost(["x", "y"], [1.0, 2.0], 3) == [["y"], ["x"], []]
    with pytest.raises(InputError, match="one cost >= 0 per item"):
        shards.deal_by_cost(["x", "y"], [1.0], 2)
    with pytest.raises(InputError, match="part count"):
        shards.deal_by_cost(["x"], [1.0], 0)


TIMINGS = ("gen_s", "compress_s", "decompress_s")


def _without(entry: dict, keys) -> dict:
    return {k: v for k, v in entry.items() if k not in keys}


def _untimed(row: dict) -> dict:
    """A row without its clock readings: the timings, and the seconds of an RDO row's optimisation and checks."""
    rdo = row["rdo"] and {**_without(row["rdo"], {"seconds", "checks"}),
                          "checks": [_without(check, {"seconds"}) for check in row["rdo"]["checks"]]}
    return {**_without(row, TIMINGS), "rdo": rdo}


def _close(a, b) -> bool:
    """Whether ``a`` and ``b`` (JSON values) are equal, floats within 1e-5 relative (1e-6 absolute)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        return a == pytest.approx(b, rel=1e-5, abs=1e-6)
    return a == b


def test_worker_seconds_give_a_line_per_worker():
    seconds = worker_seconds(3, started=100.0, entered=102.5, loaded=104.0)
    assert (seconds["units"], seconds["start_s"], seconds["load_s"]) == (3, 2.5, 1.5) and seconds["work_s"] > 0
    lines = format_worker_seconds(9.0, [seconds, {**seconds, "units": 0}], "samples").splitlines()
    assert lines[0] == "2 worker(s), 9.0 s from the split to the last result" and len(lines) == 3
    assert lines[1].startswith("  worker 0: 3 samples, start 2.5 s, load 1.5 s, work ")
    assert lines[2].startswith("  worker 1: 0 samples, start 2.5 s")


@pytest.mark.slow  # about 30 s on 2 CPU cores: three runs, two of them starting two worker processes
def test_eval_over_two_cpu_workers_writes_what_one_process_writes(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)  # no LPIPS: shorter runs
    save_pretrained(tiny_coding_model(0), tmp_path / "tiny.safetensors")
    for name, seed, views in (("a", 1, 3), ("b", 2, 2), ("c", 3, 3)):  # b has too few views: skipped
        write_scene(tmp_path / "scenes" / name, seed=seed, views=views)
    command = ["eval", "--data", str(tmp_path / "scenes"), "--protocol", "scene", "--lambdas", "64", "--baselines",
               "none", "--targets", "1", "--renders", "--device", "cpu", "--json", "--checkpoint",
               str(tmp_path / "tiny.safetensors")]
    assert main([*command, "-o", str(tmp_path / "one"), "--workers", "1"]) == 0
    capsys.readouterr()
    assert main([*command, "-o", str(tmp_path / "two"), "--workers", "2"]) == 0
    printed = json.loads(capsys.readouterr().out)  # where each worker's time went: printed, not in results.json
    assert [w["units"] for w in printed["worker_seconds"]] == [2, 0] and printed["wall_s"] > 0
    assert all(w[key] >= 0 for w in printed["worker_seconds"] for key in ("start_s", "load_s", "work_s"))
    one, two = (json.loads((tmp_path / out / "results.json").read_text()) for out in ("one", "two"))
    assert "worker_seconds" not in two
    assert list(two) == list(one) and two["plan"] == one["plan"] and two["scenes"] == ["a", "c"]
    assert len(two["rows"]) == 2 * 3 and _close([_without(r, TIMINGS) for r in two["rows"]],
                                                 [_without(r, TIMINGS) for r in one["rows"]])
    assert _close([_without(s, TIMINGS) for s in two["summary"]], [_without(s, TIMINGS) for s in one["summary"]])
    for key in ("device", "machine", "model_id", "lpips", "skipped", "samples_done", "depth_reference"):
        assert two[key] == one[key], key
    assert [s["scene"] for s in two["skipped"]] == ["b"]  # worker 1 (a, c and b dealt over two) had no usable scene
    assert _without(two["config"], {"out"}) == _without(one["config"], {"out"})
    assert two["tables"]["table1"] == one["tables"]["table1"] and two["tables"]["table3"] == one["tables"]["table3"]
    assert one["tables"]["table1"] in (tmp_path / "two" / "tables.md").read_text()
    assert os.listdir(tmp_path / "two" / "shards") == ["0"]
    assert sorted(p.name for p in (tmp_path / "two" / "renders").iterdir()) == ["a-1.png", "c-2.png"]
    assert main([*command, "-o", str(tmp_path / "two"), "--workers", "2"]) == 0  # every shard resumes: nothing to run
    assert json.loads((tmp_path / "two" / "results.json").read_text())["rows"] == two["rows"]  # timings as measured


@pytest.mark.slow  # about 30 s on 2 CPU cores: a one-process run, then two worker processes
def test_eval_with_rdo_rows_over_two_cpu_workers_writes_what_one_process_writes(tmp_path, monkeypatch):
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)  # no LPIPS: shorter runs
    save_pretrained(tiny_coding_model(0), tmp_path / "tiny.safetensors")
    for name, seed in (("a", 1), ("c", 3)):
        write_scene(tmp_path / "scenes" / name, seed=seed, views=4)
    command = ["eval", "--data", str(tmp_path / "scenes"), "--protocol", "scene", "--lambdas", "64,256",
               "--rdo-steps", "2", "--baselines", "ply", "--targets", "1", "--samples-per-scene", "2", "--device",
               "cpu", "--json", "--checkpoint", str(tmp_path / "tiny.safetensors")]
    assert main([*command, "-o", str(tmp_path / "one"), "--workers", "1"]) == 0
    assert main([*command, "-o", str(tmp_path / "two_rdo"), "--workers", "2"]) == 0  # 6 units: see the test above
    one, two = (json.loads((tmp_path / out / "results.json").read_text()) for out in ("one", "two_rdo"))
    assert list(two) == list(one) and two["plan"] == one["plan"] and len(one["plan"]) == 4
    assert [(r["scene"], r["method"], r["setting"]) for r in two["rows"]] == [
        (r["scene"], r["method"], r["setting"]) for r in one["rows"]]
    assert len(one["rows"]) == 4 * 7 and _close([_untimed(r) for r in two["rows"]],
                                                 [_untimed(r) for r in one["rows"]])
    assert _close([_without(s, TIMINGS) for s in two["summary"]], [_without(s, TIMINGS) for s in one["summary"]])
    for key in ("device", "machine", "model_id", "lpips", "skipped", "rdo", "samples_done", "depth_reference"):
        assert two[key] == one[key], key
    assert _without(two["config"], {"out"}) == _without(one["config"], {"out"})
    assert two["tables"]["table1"] == one["tables"]["table1"]
    worker = [json.loads((tmp_path / "two_rdo" / "shards" / str(k) / "results.json").read_text()) for k in range(2)]
    # by cost: one scene's base rows each (8 steps a row), then the four RDO units (2 steps a sample) two and two
    assert [len(w["rows"]) for w in worker] == [2 * 5 + 2 * 2, 2 * 5 + 2 * 2]
    assert all({r["scene"] for r in w["rows"] if r["rdo"]} == {"a", "c"} for w in worker)  # not dealt by scene
    # the workers draw no plots (the merge does); their results name none
    shards_out = tmp_path / "two_rdo" / "shards"
    assert not list(shards_out.rglob("*.png")) and all(set(w["files"]) == {"json", "markdown"} for w in worker)
    assert (tmp_path / "two_rdo" / "rate_distortion.png").is_file() and set(two["files"]) == set(one["files"])
    # the same command again: every shard resumes, nothing is run (the workers in this process: no start-up)
    monkeypatch.setattr(shards, "run_sharded", lambda task, parts, devices, **_: [task(p, CPU) for p in parts])
    monkeypatch.setattr(Evaluator, "run", None)
    assert main([*command, "-o", str(tmp_path / "two_rdo"), "--workers", "2"]) == 0
    assert json.loads((tmp_path / "two_rdo" / "results.json").read_text())["rows"] == two["rows"]
