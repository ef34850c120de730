"""CUDA's choices on CPU tensors (:func:`uvatar.avh.bake.cuda_choices.cuda_choices_on_cpu`): every switch on
within (the stencil's, the in-flight and read-ahead ones as asked), each as it was afterwards, an error too."""

from __future__ import annotations

import pytest

from uvatar.avh.bake import inputs, refine_device, refine_together, register_torch, stencil_warp
from uvatar.avh.bake.cuda_choices import cuda_choices_on_cpu

SWITCHES = [(register_torch, "WINDOW_SEARCH_ON_CPU"), (register_torch, "NEAREST_KERNEL"),
            (refine_device, "STEP_IN_WARP_ON_CPU"), (refine_device, "POSE_IN_WARP_ON_CPU"),
            (stencil_warp, "STENCIL_IN_WARP_ON_CPU"), (refine_together, "IN_FLIGHT_ON_CPU"),
            (inputs, "READ_AHEAD_ON_CPU")]


def _values():
    return [getattr(module, name) for module, name in SWITCHES]


def test_every_choice_within_and_as_before_after(monkeypatch):
    for module, name in SWITCHES:
        monkeypatch.setattr(module, name, False)
    before = _values()
    with cuda_choices_on_cpu():
        assert all(v is True for v in _values())
    assert _values() == before
    with cuda_choices_on_cpu(stencil_kernel=False, in_flight=False, read_ahead=False):
        assert _values() == [True, True, True, True, False, False, False]
    with pytest.raises(RuntimeError), cuda_choices_on_cpu():
        raise RuntimeError("a failed bake")
    assert _values() == before
