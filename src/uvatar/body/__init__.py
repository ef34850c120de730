"""Body models: one interface over skinned templates with a UV layout (anny default, SMPL/SMPL-X).

Importing this package is cheap; anny and smplx load on first use of :func:`load_body_model`.

>>> body = load_body_model("anny")                       # doctest: +SKIP
>>> posed = body.pose(torch.zeros(1, body.num_joints, 3))  # doctest: +SKIP
"""

from uvatar.body.base import BodyModel, BodyTemplate, PosedBody
from uvatar.body.masks import PART_NAMES, PartMaskConfig, part_masks, part_vertex_weights
from uvatar.body.registry import BODY_MODELS, clear_body_model_cache, load_body_model

__all__ = ["BodyModel", "BodyTemplate", "PosedBody", "load_body_model", "clear_body_model_cache",
           "BODY_MODELS", "part_masks", "part_vertex_weights", "PartMaskConfig", "PART_NAMES"]
