"""The DVA toy body: a two-joint UV-mapped tube (``body_model: "toy"`` in a capture; the tests'
capture writer is ``tests/fixtures/dva_capture.py``).

:class:`ToyBody` is :class:`uvatar.body.toy.ToyTubeBody` configured as a 1 m tube bending at
mid-height (joints "root" and "bend"; conditioning joint 1; UVs inset to [0.02, 0.98]).
"""

from __future__ import annotations

from uvatar.body.toy import ToyTubeBody, ToyTubeConfig


def dva_tube_config(n_around: int = 16, n_up: int = 12, radius: float = 0.15, height: float = 1.0) -> ToyTubeConfig:
    """Open cylinder along +Y from y = 0 to ``height``; UV u = 0.02 + 0.96 angle / 2 pi (seam split),
    v = 0.02 + 0.96 y / height. Joint 0 at the base, joint 1 at mid-height; skin weights blend
    linearly across the middle 30 % of the height."""
    return ToyTubeConfig(rings=n_up, segments=n_around, height=height, radius=radius, u_range=(0.02, 0.98),
                         joint_names=("root", "bend"), joint_parents=(-1, 0), joint_heights=(0.0, height / 2),
                         skinning="ramp", skinned_joints=None, blend=0.3, conditioning_joints=(1,),
                         semantic_joints={"pelvis": 0}, shape_names=())


class ToyBody(ToyTubeBody):
    """Two-joint LBS tube (:func:`dva_tube_config`); ``pose`` follows EasyMocap: V = R(Rh) LBS + Th."""

    def __init__(self, n_around: int = 16, n_up: int = 12, radius: float = 0.15, height: float = 1.0):
        super().__init__(config=dva_tube_config(n_around, n_up, radius, height))
