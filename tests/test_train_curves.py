"""train.curves: throughput and like-for-like loss comparison of runs, the PNG and the CLI."""

from __future__ import annotations

import json

import pytest

from codecsplat_warp.errors import InputError
from train.curves import compare, main, moving_average, throughput


def _records(steps, seconds_per_step, scenes, loss):
    return [{"step": s, "loss": loss(s), "scenes": scenes, "elapsed_s": 5.0 + s * seconds_per_step} for s in steps]


def test_throughput_leaves_out_the_start_and_counts_scenes_per_step():
    records = _records([20, 40, 60], 0.25, 2, lambda s: 1.0)  # 2 scenes every 0.25 s
    assert throughput(records) == pytest.approx(8.0)
    assert throughput([{"step": 1, "loss": 1.0}]) is None


def test_compare_means_only_over_steps_every_run_logged():
    fast = _records([20, 40, 60, 80], 0.1, 2, lambda s: 1.0 if s <= 40 else 100.0)
    slow = _records([20, 40], 0.2, 2, lambda s: 3.0)
    rows = compare({"fast": fast, "slow": slow}, ["loss"])
    assert [r["mean loss (steps 20-40)"] for r in rows] == [1.0, 3.0]
    assert [r["scenes/s"] for r in rows] == [20.0, 10.0]
    with pytest.raises(InputError, match="no logged step in common"):
        compare({"a": fast, "b": _records([30], 0.1, 2, lambda s: 1.0)}, ["loss"])


def test_cli_writes_the_plot_and_the_table(tmp_path, capsys):
    for name, rate in (("a", 0.1), ("b", 0.05)):
        (tmp_path / name).mkdir()
        lines = [json.dumps(r) for r in _records([20, 40, 60], rate, 2, lambda s: 1.0 / s)]
        (tmp_path / name / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    main([str(tmp_path / "a"), str(tmp_path / "b"), "--labels", "one", "two", "--metrics", "loss",
          "--against-time", "--smooth", "2", "--out", str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")])
    assert (tmp_path / "c.png").stat().st_size > 5000
    assert [r["run"] for r in json.loads((tmp_path / "c.json").read_text())] == ["one", "two"]
    assert "| one |" in capsys.readouterr().out
    with pytest.raises(InputError, match="2 runs but 1 labels"):
        main([str(tmp_path / "a"), str(tmp_path / "b"), "--labels", "x", "--out", str(tmp_path / "d.png")])


def test_runs_that_recorded_their_process_count_get_the_scaling_efficiency(tmp_path, capsys):
    for name, world, rate in (("one", 1, 0.1), ("four", 4, 0.2)):  # 20 and 40 scenes/s: half of linear
        (tmp_path / name).mkdir()
        lines = [json.dumps(r) for r in _records([20, 40, 60], rate, 2 * world, lambda s: 1.0)]
        (tmp_path / name / "metrics.jsonl").write_text("\n".join(lines) + "\n")
        (tmp_path / name / "config.json").write_text(json.dumps({"train": {}, "model": {}, "world_size": world}))
    runs = [str(tmp_path / "one"), str(tmp_path / "four")]
    main([*runs, "--metrics", "loss", "--out", str(tmp_path / "s.png"), "--json", str(tmp_path / "s.json")])
    rows = json.loads((tmp_path / "s.json").read_text())
    assert [(r["GPUs"], r["scaling"]) for r in rows] == [(1, 1.0), (4, 0.5)]
    assert "| four |" in capsys.readouterr().out
    (tmp_path / "four" / "config.json").write_text(json.dumps({"train": {}, "model": {}}))  # written before it
    main([*runs, "--metrics", "loss", "--out", str(tmp_path / "s.png"), "--json", str(tmp_path / "s.json")])
    assert all("scaling" not in r for r in json.loads((tmp_path / "s.json").read_text()))


def test_moving_average_is_trailing():
    assert moving_average([1.0, 3.0, 5.0, 7.0], 2) == [1.0, 2.0, 4.0, 6.0]
    assert moving_average([1.0, 3.0], 1) == [1.0, 3.0]
