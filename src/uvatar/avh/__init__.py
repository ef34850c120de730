"""AVH (Animatable Virtual Humans): bake scans into body UV space, train, export, animate.

Sub-packages are imported where used: ``uvatar.avh.bake`` (stage 1: shadow mesh, registration,
texel correspondences, confidence, inpainting, frame rejection and selection), then the model,
training, export and animation modules.
"""
