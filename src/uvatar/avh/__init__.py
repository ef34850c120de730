"""AVH (Animatable Virtual Humans): bake scans into body UV space, train, export, animate.

Sub-packages are imported where used: ``uvatar.avh.bake`` (stage 1: shadow mesh, registration,
texel correspondences, confidence, inpainting, frame rejection and selection), then the model,
training, export and animation modules.
"""


def __getattr__(name: str):
    """``uvatar.avh.FastGenerator`` / ``InferenceConfig``: the generator for inference in bf16 / fp16,
    compiled (:mod:`uvatar.avh.inference`), imported on first use."""
    if name in ("FastGenerator", "InferenceConfig"):
        from uvatar.avh import inference

        return getattr(inference, name)
    raise AttributeError(f"module 'uvatar.avh' has no attribute {name!r}")
