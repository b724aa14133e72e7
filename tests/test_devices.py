"""`resolve_device`: every device a config can name is checked up front, with one line naming the key."""

import pytest
import torch

from degusta_learn.devices import resolve_device
from degusta_learn.errors import DegustaError


def test_auto_and_cpu_resolve():
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("cpu:0") == "cpu:0"


@pytest.mark.parametrize("device", ["tpu", "", "cuda:x", "gpu", "cuda:-1", " cpu"])
def test_not_a_device_is_one_line_naming_the_key(device):
    with pytest.raises(DegustaError, match=r"^backend\.device: ") as err:
        resolve_device(device, "backend.device")
    assert "\n" not in str(err.value)


def test_a_cuda_index_past_the_visible_devices_is_refused():
    with pytest.raises(DegustaError, match=r"^device: 'cuda:64' requested but"):
        resolve_device("cuda:64")


def test_a_machine_without_the_device_says_so():
    if torch.cuda.is_available():
        pytest.skip("needs a machine without a CUDA device")
    with pytest.raises(DegustaError, match="no CUDA device is visible"):
        resolve_device("cuda", "backend.device")
    if not torch.backends.mps.is_available():
        with pytest.raises(DegustaError, match="no Apple GPU"):
            resolve_device("mps")
