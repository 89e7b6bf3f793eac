"""Weight average (EMA) of training runs: the update rule."""

from __future__ import annotations

import pytest
import torch

from codecsplat_warp.errors import InputError
from train.weight_average import WeightAverage, warmed_up_decay


def test_update_averages_only_trainable_parameters_with_the_warmed_up_decay():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Linear(2, 1)).double()
    model[1].requires_grad_(False)
    average = WeightAverage(model, decay=0.5)
    assert set(average.averages) == {"0.weight", "0.bias"}
    assert all(a.dtype == torch.float32 for a in average.averages.values())
    expected = model[0].weight.detach().float().clone()
    for n in range(12):
        with torch.no_grad():
            model[0].weight.add_(1.0)
        keep = min(0.5, (1 + n) / (10 + n))
        assert warmed_up_decay(0.5, n) == pytest.approx(keep)
        expected = keep * expected + (1 - keep) * model[0].weight.detach().float()
        average.update(model)
        torch.testing.assert_close(average.averages["0.weight"], expected)
    assert average.updates == 12 and warmed_up_decay(0.5, 11) == 0.5 and warmed_up_decay(0.999, 0) == 0.1
    with pytest.raises(InputError, match="decay"):
        WeightAverage(model, decay=1.0)
