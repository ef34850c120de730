"""uvatar.devices: the device-name check, and the helpers that keep a hot path from copying host data to
the device (a blocking copy synchronises the stream) on every call."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch

from uvatar.devices import check_device, on_device, to_device_async, to_numpy
from uvatar.errors import InputError


def test_check_device():
    assert check_device("cpu") == "cpu"
    with pytest.raises(InputError, match="is not a device"):
        check_device("bogus")


def test_on_device_copies_an_array_once_while_it_lives():
    faces = np.arange(12, dtype=np.int32).reshape(4, 3)
    a = on_device(faces, "cpu", torch.long)
    assert a.dtype == torch.long and torch.equal(a, torch.as_tensor(faces).long())
    assert on_device(faces, "cpu", torch.long) is a  # kept: no second copy
    assert on_device(faces, "cpu") is not a and on_device(faces, "cpu").dtype == torch.int32  # per dtype
    other = faces.copy()
    assert on_device(other, "cpu", torch.long) is not a  # another array, another copy
    as_list = [[0, 1, 2]]
    assert on_device(as_list, "cpu") is on_device(as_list, "cpu")  # not weakly referenceable: kept alive
    del faces, a
    gc.collect()
    fresh = np.zeros((2, 3), np.int32)  # may reuse the freed array's id: never its stale copy
    assert torch.equal(on_device(fresh, "cpu", torch.long), torch.zeros(2, 3, dtype=torch.long))


def test_to_device_async_keeps_values_and_dtype():
    x = np.linspace(0, 1, 7)
    t = to_device_async(x, "cpu", torch.float32)
    assert t.dtype == torch.float32 and torch.allclose(t, torch.as_tensor(x, dtype=torch.float32))
    assert torch.equal(to_device_async(torch.arange(3), "cpu"), torch.arange(3))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_copies_never_sync():
    x = np.random.default_rng(0).random((64, 3))
    on_device(x, "cuda")
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        y = to_device_async(x, "cuda", torch.float32)
        z = on_device(x, "cuda")
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert torch.allclose(y.cpu(), torch.as_tensor(x, dtype=torch.float32)) and z.is_cuda


def test_to_numpy_on_the_cpu_is_the_tensors_own_memory():
    """On the CPU ``to_numpy`` is ``detach().cpu().numpy()``: the values, the dtype, the same memory (no
    copy), a tensor that requires grad detached."""
    t = torch.linspace(0, 1, 12, dtype=torch.float64).reshape(3, 4).requires_grad_()
    a = to_numpy(t)
    assert isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (3, 4)
    np.testing.assert_array_equal(a, t.detach().numpy())
    m = torch.tensor([True, False, True])
    b = to_numpy(m)
    b[1] = True
    assert bool(m[1]) and b.dtype == bool


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_to_numpy_from_cuda_through_pinned_memory():
    """From CUDA: the same values as ``.cpu().numpy()``, for a strided view and float16 / bool / int64
    dtypes; the array owns pinned memory that outlives the tensor it came from."""
    base = torch.rand(64, 32, device="cuda", dtype=torch.float32)
    for t in (base, base.T, base[::2, 3:7], base.half(), base > 0.5, (base * 100).long()):
        a = to_numpy(t)
        np.testing.assert_array_equal(a, t.cpu().numpy())
    a = to_numpy(torch.full((1024, 1024), 3.0, device="cuda"))
    gc.collect()
    torch.cuda.synchronize()
    assert a.shape == (1024, 1024) and (a == 3.0).all()
