"""The stiff and extreme cases catalog (``codecsplat_warp.bench.extreme``, issue 8), one test per case and device.

Each accuracy case must give finite outputs and gradients and stay within its stated bounds against the float64
reference; each invalid-input case must raise its typed error naming the argument. Cases marked ``known_bug``
are strict xfails (fixing the bug must remove the mark); ``cuda_only`` cases are skipped on the CPU.
"""

from __future__ import annotations

import json

import pytest
import torch
from conftest import DEVICES

from codecsplat_warp.bench import extreme
from codecsplat_warp.bench.extreme import CASES, call, measure_accuracy


def _case_params() -> list:
    params = []
    for case in CASES:
        for device in DEVICES:
            name = device.values[0]
            marks = list(device.marks)
            if case.cuda_only and name == "cpu":
                marks.append(pytest.mark.skip(reason=f"CUDA only: {case.note}"))
            if case.known_bug:
                marks.append(pytest.mark.xfail(strict=True, reason=case.known_bug))
            params.append(pytest.param(case, name, id=f"{case.name}-{name}", marks=marks))
    return params


@pytest.mark.parametrize("case, device", _case_params())
def test_extreme_case(case, device):
    if case.error is not None:
        with pytest.raises(case.error, match=case.match):
            call(case, device)
        return
    result = measure_accuracy(case, device)
    assert result["finite_fwd"], "non-finite output"
    assert result["finite_bwd"], "non-finite gradient"
    assert result["err_fwd"] <= case.bound, f"output error {result['err_fwd']:.2e} > {case.bound:.0e}"
    bound = case.gradient_bound
    assert result["err_bwd"] <= bound, f"gradient error {result['err_bwd']:.2e} > {bound:.0e}"


def test_catalog_states_a_bound_or_an_error_for_every_case():
    names = [c.name for c in CASES]
    assert len(CASES) >= 25 and len(set(names)) == len(names)
    for case in CASES:
        if case.error is None:
            assert case.bound is not None and case.gradient_bound is not None, case.name
            assert 0 < case.bound < 1 and 0 < case.gradient_bound < 1, case.name
        else:
            assert case.bound is None and case.match, case.name
    covered = {c.op.name for c in CASES}
    assert {"unproject", "reproject_average", "plane_sweep_cost_volume", "rasterize"} <= covered


def test_relative_error_and_strict_known_bug_verdict():
    ref = torch.tensor([0.0, 2.0, -4.0], dtype=torch.float64)
    assert extreme.relative_error(ref + torch.tensor([0.0, 0.004, 0.0]), ref) == pytest.approx(1e-3)
    assert extreme.relative_error(torch.full((2,), 3e-7), torch.zeros(2)) == pytest.approx(3e-7)
    assert not extreme.relative_error(torch.tensor([float("nan")]), torch.ones(1)) <= 1.0  # NaN passes no bound
    rows = [{"ok": True, "known_bug": None}, {"ok": None, "known_bug": None}, {"ok": False, "known_bug": "x"}]
    assert extreme.catalog_passed(rows)
    assert not extreme.catalog_passed(rows + [{"ok": True, "known_bug": "fixed but still marked"}])
    assert not extreme.catalog_passed(rows + [{"ok": False, "known_bug": None}])


def test_script_prints_the_table_and_writes_json(tmp_path, capsys):
    out = tmp_path / "extreme.json"
    code = extreme.main(["--device", "cpu", "--cases", "rasterize-1x1-image,unproject-nan-depth", "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "| rasterize-1x1-image | float32 | True | True |" in printed and "ok (InputError)" in printed
    result = json.loads(out.read_text())
    assert [r["case"] for r in result["rows"]] == ["rasterize-1x1-image", "unproject-nan-depth"]
    assert result["passed"] and result["rows"][0]["err_fwd"] <= result["rows"][0]["bound"]
