"""The synthetic studio: a capture (scans, fits, multi-view images) of a clothed person made from
the body model, with exact ground truth in ``OUT/gt/`` (see docs/ARCHITECTURE.md).

>>> from uvatar.capture.synth import preset, synthesize      # doctest: +SKIP
>>> synthesize("/tmp/cap", preset("quick", frames=8))         # doctest: +SKIP

Modules: ``motion`` (takes, held-out poses) on ``dofs``; ``surface``, ``appearance``, ``clothing``
and ``bends`` (ground-truth texture and clothing as functions of body-surface features);
``scans`` (topologies, atlases, broken frames); ``fits``; ``cameras``; ``images``; ``gt``;
``frame`` (one frame); ``pipeline`` (planning, parallel frames, resume); ``preview``. The studio's
benchmark is ``bench/synth.py``.
"""

from uvatar.capture.synth.config import PRESETS, SynthConfig, preset
from uvatar.capture.synth.motion import TAKE_NAMES, Takes, make_heldout, make_takes
from uvatar.capture.synth.pipeline import make_plan, synthesize

__all__ = ["SynthConfig", "PRESETS", "preset", "synthesize", "make_plan", "make_takes", "make_heldout",
           "Takes", "TAKE_NAMES"]
