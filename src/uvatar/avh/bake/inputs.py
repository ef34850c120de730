"""What a bake worker loads: the body model with its UV layout at R texels (memoized once per
process, or adopted from the parent so a worker does not raster it again), and a frame's starting
fit with the shape to pose it by. Shared by the per-frame bake (:mod:`.pipeline`) and the refinement
across frames (:mod:`.refine_together`)."""

from __future__ import annotations

__all__ = ["load_body_and_layout", "adopt_body_and_layout", "start_fit"]

# -- per-process state ----------------------------------------------------------------------------
_STATE: dict = {}


def load_body_and_layout(body_name: str, texels: int):
    """(BodyModel, BodyLayout) for a body model at a texel resolution; memoized per process."""
    key = (body_name, int(texels))
    if key not in _STATE:
        from uvatar.avh.bake.frame import BodyLayout
        from uvatar.body import load_body_model

        body = load_body_model(body_name)
        _STATE[key] = (body, BodyLayout.from_template(body.template, texels))
    return _STATE[key]


def adopt_body_and_layout(body_name: str, texels: int, pair):
    """Keep ``pair`` (BodyModel, BodyLayout), shipped from the parent process, unless this process
    already holds one for the same body and resolution; returns the one held."""
    return _STATE.setdefault((body_name, int(texels)), pair)


def start_fit(capture, frame: str):
    """(the capture's fit of ``frame``, the shape to pose it with: None when the fit carries its own,
    else the capture's shared shape if it has one)."""
    fit = capture.load_fit(frame)
    if fit.shapes.size:
        return fit, None
    shapes = capture.body_shapes
    return fit, shapes if shapes.size else None
