"""Which ray caster runs a query: Embree (:class:`uvatar.geometry.raycast.RayCaster`, the CPU default) or
Warp's mesh BVH (:class:`uvatar.geometry.raycast_warp.WarpRayCaster`, CUDA and CPU). The one place that
chooses, so the bake and the tests ask the same question the same way."""

from __future__ import annotations

from uvatar.errors import InputError
from uvatar.geometry.raycast import RayCaster, RayCasterConfig

__all__ = ["RAY_BACKENDS", "make_caster"]

RAY_BACKENDS = ("auto", "embree", "warp")


def make_caster(vertices, faces, config: RayCasterConfig | None = None, device: str = "cpu",
                backend: str = "auto") -> RayCaster:
    """The ray caster for ``device``: ``backend`` "auto" is Embree on the CPU (the fastest there) and
    Warp's mesh BVH on CUDA (:class:`uvatar.geometry.raycast_warp.WarpRayCaster`); "embree" or "warp"
    force one (Warp also runs on the CPU, single-threaded). Same queries and results either way."""
    if backend not in RAY_BACKENDS:
        raise ValueError(f"ray backend must be one of {RAY_BACKENDS}, got {backend!r}")
    on_cpu = str(device) == "cpu"
    if backend == "embree" or (backend == "auto" and on_cpu):
        if not on_cpu:
            raise InputError("device", f"{device}: Embree runs on the CPU only (use the warp ray backend)")
        return RayCaster(vertices, faces, config)
    from uvatar.geometry.raycast_warp import WarpRayCaster  # imports warp (the kernels extra) only when asked

    return WarpRayCaster(vertices, faces, config, device=str(device))
