"""The CUDA bake's choices made on CPU tensors: one owner of the switches that a machine without a GPU
(CI, this project's usual machine) sets to run ``uvatar bake --device cuda``'s operations on the CPU
(issue 39), for ``scripts/gpu_path_bake.py`` and ``bench/bake.py --count-ops``.

Where the bake's torch device is CUDA it takes, and on the CPU it leaves to its twins unless told: the
nearest samples through the Warp grid kernel, the refinement's body posed in Warp and its step in its
Warp kernel, the colour stencil in its Warp kernel, the frames dealt into tasks of frames in flight, and
the next task's scans read ahead.
"""

from __future__ import annotations

import contextlib

__all__ = ["cuda_choices_on_cpu"]


@contextlib.contextmanager
def cuda_choices_on_cpu(stencil_kernel: bool = True, in_flight: bool = True, read_ahead: bool = True):
    """Within: the bake makes CUDA's choices on CPU tensors (module doc; ``stencil_kernel``: the stencil
    in Warp, else its torch twin; ``in_flight``, ``read_ahead``: those choices too); as before afterwards."""
    from uvatar.avh.bake import inputs, refine_device, refine_together, register_torch, stencil_warp

    switches = [(register_torch, "WINDOW_SEARCH_ON_CPU", True), (register_torch, "NEAREST_KERNEL", True),
                (refine_device, "STEP_IN_WARP_ON_CPU", True), (refine_device, "POSE_IN_WARP_ON_CPU", True),
                (stencil_warp, "STENCIL_IN_WARP_ON_CPU", stencil_kernel),
                (refine_together, "IN_FLIGHT_ON_CPU", in_flight), (inputs, "READ_AHEAD_ON_CPU", read_ahead)]
    saved = [(module, name, getattr(module, name)) for module, name, _ in switches]
    for module, name, value in switches:
        setattr(module, name, value)
    try:
        yield
    finally:
        for module, name, value in saved:
            setattr(module, name, value)
