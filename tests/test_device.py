import pytest
import torch

from render.device import pick_device, torch_threads
from render.errors import SineError


def test_auto_device_is_cpu_without_cuda_and_forcing_cuda_fails_clearly():
    if torch.cuda.is_available():
        pytest.skip("machine has CUDA")
    assert pick_device("auto") == torch.device("cpu")
    assert pick_device("cpu") == torch.device("cpu")
    with pytest.raises(SineError, match="no CUDA device"):
        pick_device("cuda")


def test_torch_threads_sets_and_restores_the_thread_count():
    before = torch.get_num_threads()
    other = 1 if before != 1 else 2
    with torch_threads(other):
        assert torch.get_num_threads() == other
    assert torch.get_num_threads() == before
    with torch_threads(0):  # 0: unchanged
        assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(other):
        raise RuntimeError("restored on errors too")
    assert torch.get_num_threads() == before
