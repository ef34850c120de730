"""uvatar: animatable (AVH) and drivable (DVA) human avatars learned in body UV space.

Sub-packages follow the pipeline:

- :mod:`uvatar.body`      skinned body models with a UV layout (anny default, SMPL/SMPL-X via smplx)
- :mod:`uvatar.geometry`  UV rasterization, texel sampling, tangent frames, ray casting, subdivision
- :mod:`uvatar.capture`   capture folder format, readers/writers, validation, the synthetic studio
- :mod:`uvatar.motion`    BVH / AMASS / EasyMocap motions retargeted onto a body model
- :mod:`uvatar.render`    textured-mesh renderer, cameras, image metrics, videos and reports
- :mod:`uvatar.avh`       Animatable Virtual Humans: bake, select, train, export, animate, eval
- :mod:`uvatar.dva`       Drivable Volumetric Avatars: primitives, texel-aligned features, ray marching
- :mod:`uvatar.cli`       thin command-line front end (``uvatar --help``)
"""

__version__ = "0.1.0"
