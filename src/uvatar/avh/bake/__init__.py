"""AVH stage 1: bake textured scans into the body's UV space (AVH paper §3.2, §3.4).

Per frame: the shadow mesh M^S_t (body posed by the fit) is registered to the scan (M^R_t), each
texel casts two rays along +/- its normal to the scan, and the texture, displacement d = x - s and
confidence kappa = v * w * delta * nms are stored; unmatched texels are inpainted (Telea). Across
frames: frames with mean kappa < 130/255 are rejected, and k-means on joint-angle cosines selects the
training poses.

Public API::

    BakeConfig, RegistrationConfig                      # config.py
    BodyLayout, BakedFrame, bake_frame, shadow_vertices  # frame.py (functional core)
    bake_capture, bake_selection                        # pipeline.py (folders, workers, resume)
    SelectConfig, select_frames, select_from_baked, select_from_capture   # select.py
    EvalConfig, evaluate_bake                           # evaluate.py
    cuda_choices_on_cpu                                 # cuda_choices.py (check the GPU bake without a GPU)
"""

from uvatar.avh.bake.config import BakeConfig, RegistrationConfig
from uvatar.avh.bake.cuda_choices import cuda_choices_on_cpu

__all__ = [
    "BakeConfig", "RegistrationConfig", "BodyLayout", "BakedFrame", "bake_frame", "shadow_vertices",
    "bake_capture", "bake_selection", "SelectConfig", "select_frames", "select_from_baked",
    "select_from_capture", "EvalConfig", "evaluate_bake", "cuda_choices_on_cpu",
]

_LAZY = {
    "BodyLayout": "frame", "BakedFrame": "frame", "bake_frame": "frame", "shadow_vertices": "frame",
    "bake_capture": "pipeline", "bake_selection": "pipeline",
    "SelectConfig": "select", "select_frames": "select", "select_from_baked": "select",
    "select_from_capture": "select", "EvalConfig": "evaluate", "evaluate_bake": "evaluate",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"uvatar.avh.bake.{_LAZY[name]}"), name)
    raise AttributeError(name)
