"""Exporters of a trained avatar for other runtimes: :mod:`.engine` writes the engine bundle (a skinned
GLB written by :mod:`.glb` plus a manifest for the ONNX generator) that the browser viewer and game
engines load. ``uvatar export`` (:mod:`uvatar.avh.export`) calls it after writing the ONNX model."""
