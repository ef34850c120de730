"""The torch-Warp bridge (:mod:`uvatar.geometry.warp_torch`, one owner for every kernel's launches): a view
of a tensor keeps it alive to the launch that takes it, reads and writes the tensor's own memory, and a
launch on the CPU goes on no stream."""

from __future__ import annotations

import gc
import weakref

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("warp")

from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_types, warp_view  # noqa: E402


def _copy_kernel():
    wp = load_warp()

    @wp.kernel
    def copy(src: wp.array(dtype=wp.vec3d), dst: wp.array(dtype=wp.vec3d)):
        i = wp.tid()
        dst[i] = src[i] * wp.float64(2.0)

    return copy


def test_a_view_of_a_temporary_keeps_it_alive_to_the_launch():
    """``warp_view(wp, x.to(float64))``: the temporary lives as long as the view (Warp's descriptor alone
    holds only its address), and the launch reads its values, with other tensors made and freed between
    the view and the launch; the output view writes the tensor itself."""
    wp = load_warp()
    source = torch.arange(12, dtype=torch.float32).reshape(4, 3)
    temporary = source.to(torch.float64)
    alive = weakref.ref(temporary)
    view = warp_view(wp, temporary, wp.vec3d)
    del temporary
    gc.collect()
    assert alive() is not None                      # kept by the view
    for _ in range(8):                              # memory the allocator could hand out again
        torch.full((4, 3), -1.0, dtype=torch.float64)
    out = torch.zeros(4, 3, dtype=torch.float64)
    wp.launch(_copy_kernel(), dim=4, inputs=[view, warp_view(wp, out, wp.vec3d)], device="cpu",
              stream=launch_stream(out.device))
    assert torch.equal(out, 2 * source.double())
    del view
    gc.collect()
    assert alive() is None                          # and no longer than the view


def test_the_bridge_types_and_streams():
    """float32 and float64 tensors get Warp's vectors of that scalar; a CPU device launches on no stream;
    Warp loads once (the same module)."""
    wp = load_warp()
    assert load_warp() is wp
    v3, v4, m33 = warp_types(wp, torch.float64)
    assert v3 is wp.types.vector(3, wp.float64) and v4._length_ == 4 and m33._shape_ == (3, 3)
    assert warp_types(wp, torch.float32)[0]._wp_scalar_type_ is wp.float32
    assert launch_stream(torch.device("cpu")) is None
