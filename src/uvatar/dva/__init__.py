"""DVA: drivable volumetric avatars (Remelli et al. 2022) on the uvatar body model and capture format.

Modules: ``raymarch_ref`` (the renderer's specification, brute force), ``raymarch`` (fast torch twin)
and ``raymarch_warp`` (fused Warp kernels, CPU and CUDA),
``primitives`` (LBS-articulated W x W UV-grid primitives), ``features`` (texel-aligned pose / image /
view features), ``decoders`` (untied-bias conv branches), ``losses``, ``model`` (DvaModel, DvaConfig,
presets), ``data`` (capture / EasyMocap / ZJU-MoCap sources and protocols), ``dataset`` (in-memory
frame bank), ``train``, ``drive`` (render from poses + driving views), ``eval``, ``toy`` (a tiny
test body and capture). CLI: ``uvatar train dva``, ``uvatar render dva``, ``uvatar eval dva``.
"""
