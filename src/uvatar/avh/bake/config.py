"""Configuration of AVH stage 1 (baking scans into body UV space).

Every constant of the paper (§3.2, §3.4 of animatable-virtual-humans.md) is a field here; the CLI
flags of ``uvatar bake`` map one to one onto these fields (no second source of defaults).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace

from uvatar.errors import check_values

STAGE_MODES = ("closest", "rays", "normal")
TORCH_STAGES = ("auto", "on", "off")


@dataclass(frozen=True)
class RegistrationConfig:
    """Progressive non-rigid registration of the shadow mesh to the scan (Morgenstern et al. 2019).

    Runs after the articulated fit refinement (:class:`PoseRefineConfig`, the stiffest stage). Each
    stage s solves a sparse linear least-squares problem with a uniform graph Laplacian L (so the
    stiffness is dimensionless), ``iterations_s`` times with fresh matches c_i: "closest"/"rays"
    stages ``min_X sum_i w_i |x_i - c_i|^2 + k_s |L X - L X_shadow|^2``; "normal" stages move each
    vertex along its normal by h_i, ``min_h sum_i w_i (h_i - t_i)^2 + k_s |L h|^2``. The default is
    normal stages only, stiff to flexible: on `uvatar synth` captures, vector stages after the pose
    refinement slid vertices tangentially (median error 2.6 mm vs 1.9 mm with normal stages).

    stiffness: Laplacian weight per stage, coarse (stiff) to fine (flexible).
    iterations: solves per stage (same length as ``stiffness``).
    max_distance: per stage, matches farther than this fraction of the fit's bounding-box diagonal
        are rejected.
    max_normal_angle_deg: a match whose scan normal deviates more than this from the vertex normal
        is rejected (normal compatibility).
    modes: per stage, "closest" (targets: hits of rays along +/- the normal and the foot point of the
        closest scan sample, which also corrects tangential offsets), "rays" (ray hits only) or
        "normal" (vertices move only along their normals by a smooth scalar offset).
    anchor_weight: tiny pull toward the previous iterate; keeps the system definite for vertices
        without any match.
    normal_smoothing: "normal" stages move vertices along their normals Gaussian-averaged over this
        length (metres; 0 = the raw vertex normals), the bending length of the cloth: a garment
        cannot follow body detail finer than that, so it stands off along the low-passed normal.
    """

    stiffness: tuple[float, ...] = (30.0, 3.0)
    iterations: tuple[int, ...] = (1, 2)
    max_distance: tuple[float, ...] = (1 / 25, 1 / 50)
    modes: tuple[str, ...] = ("normal", "normal")
    max_normal_angle_deg: float = 60.0
    anchor_weight: float = 1e-4
    normal_smoothing: float = 0.03

    def __post_init__(self) -> None:
        n = len(self.stiffness)
        if not (len(self.iterations) == len(self.max_distance) == len(self.modes) == n):
            raise ValueError("registration stiffness, iterations, max_distance and modes "
                             "must have one entry per stage")
        unknown = [m for m in self.modes if m not in STAGE_MODES]
        if unknown:
            raise ValueError(f"unknown registration stage mode {unknown[0]!r}; expected one of {STAGE_MODES}")
        if self.normal_smoothing < 0:
            raise ValueError(f"registration normal_smoothing must be >= 0 metres, got {self.normal_smoothing}")


@dataclass(frozen=True)
class PoseRefineConfig:
    """iterations: Gauss-Newton steps; max_distance: match limit as a fraction of the bounding-box
    diagonal; max_normal_angle_deg: normal compatibility of matches; huber: robust (IRLS) scale in
    metres; damping: Levenberg-Marquardt factor on the diagonal; prior: pull of each update toward zero
    (joint and root rotations, translation, clothing offsets), per matched vertex, in metres^2 per
    radian^2 or per metre^2; pose_prior: pull of each conditioning joint back toward its rotation at the
    start of the refinement (``weight/2 |log(L0^T L)|^2`` per matched vertex, m^2 per rad^2): ``prior``
    damps each step, so along a turn the scan barely constrains (a limb about its own axis, a clavicle
    against its shoulder) the pose crept on at every iteration and never settled (on the real take,
    45 iterations instead of 15 moved joints by up to 10 deg); with 1e-4 the same two differ by < 0.25
    deg and the poses are smoother over frames, but they stop short of the scan (the real take's eval:
    geometry 3.7 -> 4.2 mm, -0.6 dB for every method), so it is off (0) by default;
    max_step_deg: cap on one update;
    max_vertices: evenly spread subset of shadow vertices used for matching (None = all);
    max_untracked_weight: vertices with more skinning weight than this on joints the refinement does
    not move (fingers, metacarpals, toes, eyes: not among the body's conditioning joints) are left
    out of the matching. Body-only fits (SMPL, EasyMocap) keep flat hands while the scanned
    performer curls the fingers; those vertices would drag the wrist and forearm (16 deg of wrist
    error and +3 dB of texture error on the forearms of a `uvatar synth` capture without this).

    Cross-frame colour consistency (:mod:`uvatar.avh.bake.photometric`), for a bake of several
    frames: after the geometric refinement of every frame, one round per entry of
    ``photometric_radii`` (stencil radius in metres, coarse to fine; () = off) re-refines each frame
    with its colours pulled toward the median over frames; photometric_weight: weight of a squared
    colour error (RGB in [0, 1]) against a squared metre of surface distance; photometric_huber:
    robust scale of the colour error; photometric_max_distance: how far (metres) a vertex looks along
    its normal for the scan's colour; photometric_iterations: Gauss-Newton steps per colour round
    (None: ``iterations``); photometric_min_frames: the term runs only when at least this
    many frames are refined together, and a vertex has a reference only where this many frames saw
    it. photometric_space: "rgb", or "chromaticity" (each colour divided by the sum of its channels,
    which the shading of white lights does not change: for captures whose light turns with the body).

    cuda_graph: with the torch stages on CUDA, replay the refinement's iterations after its first from one
    CUDA graph (:mod:`.refine_device`; issue 39: the host launched each iteration's hundreds of operators).
    Off by default until a lent GPU has measured it; a failed capture runs the iterations eagerly."""

    iterations: int = 15
    max_distance: float = 1 / 20
    max_normal_angle_deg: float = 60.0
    huber: float = 0.005
    damping: float = 1e-3
    prior: float = 1e-4
    pose_prior: float = 0.0
    max_step_deg: float = 10.0
    max_vertices: int | None = 4000
    max_untracked_weight: float = 0.5
    photometric_radii: tuple[float, ...] = (0.006, 0.003, 0.002)
    photometric_weight: float = 1e-2
    photometric_huber: float = 0.1
    photometric_max_distance: float = 0.03
    photometric_iterations: int | None = 8
    photometric_min_frames: int = 3
    photometric_space: str = "rgb"
    cuda_graph: bool = False

    def __post_init__(self) -> None:
        check_values([
            (self.iterations >= 0, f"pose_refine iterations must be >= 0, got {self.iterations}"),
            (self.pose_prior >= 0, f"pose_refine pose_prior must be >= 0, got {self.pose_prior}"),
            (0.0 <= self.max_untracked_weight <= 1.0,
             f"pose_refine max_untracked_weight must be in [0, 1], got {self.max_untracked_weight}"),
            (self.max_vertices is None or self.max_vertices >= 1,
             f"pose_refine max_vertices must be >= 1, got {self.max_vertices}"),
            (all(r > 0 for r in self.photometric_radii),
             f"pose_refine photometric_radii must be > 0 metres, got {self.photometric_radii}"),
            (self.photometric_weight >= 0, f"pose_refine photometric_weight must be >= 0, got {self.photometric_weight}"),
            (self.photometric_huber > 0, f"pose_refine photometric_huber must be > 0, got {self.photometric_huber}"),
            (self.photometric_max_distance > 0,
             f"pose_refine photometric_max_distance must be > 0, got {self.photometric_max_distance}"),
            (self.photometric_iterations is None or self.photometric_iterations >= 0,
             f"pose_refine photometric_iterations must be >= 0, got {self.photometric_iterations}"),
            (self.photometric_min_frames >= 2,
             f"pose_refine photometric_min_frames must be >= 2, got {self.photometric_min_frames}"),
            (self.photometric_space in ("rgb", "chromaticity"),
             f"pose_refine photometric_space must be 'rgb' or 'chromaticity', got {self.photometric_space!r}")])


@dataclass(frozen=True)
class BakeConfig:
    """Options of the per-frame bake and of the frame rejection (paper defaults).

    texels: UV map resolution R (the paper uses 1024).
    refine_pose: first refine the fit's joint rotations and Rh/Th against the scan (articulated
        ICP, the coarsest registration stage; the refined pose is what is stored).
    register: run the pairwise registration (False = ablation: rays start on the shadow mesh).
    polarity_rule: apply the normal-polarity rule when both rays hit (False = ablation: nearest).
    polarity_ratio: a positive match is preferred unless it is more than this times farther than
        the negative one (paper: 2).
    max_match_distance: texel ray hits farther than this (metres) are no match (None: no limit, as in
        the paper; they would get zero confidence from the distance term anyway).
    ray_epsilon: rays start this far (metres) behind their origin so a surface through it is found.
    visibility_rays: hemisphere rays per face centroid for the visibility terms v and w (paper: 64;
        default 16 with ``visibility_stratified``: see there).
    visibility_stratified: each face casts its own shifted and turned lattice
        (:func:`uvatar.avh.bake.confidence.face_lattice_params`) instead of one shared lattice, so the
        errors of few rays per face average out over the faces around a vertex. 16 stratified rays
        keep the vertex visibility of a 110k-face scan within 0.011 on average (0.055 at the 99th
        percentile) of the paper's 64 shared rays, for a quarter of the rays (docs/scale.md).
    distance_clip: the distance term delta clips at this fraction of the fit's bounding-box diagonal
        (paper: 1/50).
    inpaint_radius: Telea inpainting radius in texels (paper: 3).
    inpaint_band: texels farther than this (in texels) from any matched texel are first filled with
        their nearest matched value, so Telea only marches a band around the islands (speed; None =
        Telea everywhere).
    inpaint_gutter: Telea marches only inside the UV islands and this many texels around them (a
        bilinear or mipmapped lookup at an island's border reads a few texels outside it); farther
        unmatched texels take their nearest matched value (None = no limit). 4 texels leave the island
        texels' values within rounding of marching the whole band, for about a third of the march
        (docs/scale.md).
    reject_kappa: frames whose mean kappa over the body's surface texels is below this are rejected
        (paper: 130/255). Surface texels: valid texels whose rest-pose visibility on the body
        template itself exceeds ``interior_visibility``. Interior parts of the template (anny's
        eyeballs and mouth interior, 4.1 % of its texels) are never visible in any scan, so their
        kappa is always 0; SMPL's layout, for which the paper chose 130/255, has none.
    reject_colour_ratio: frames whose scan colours at the body's refinement points disagree with the
        median over the bake's frames (median |colour - reference|, from the colour rounds of
        ``pose_refine``) by more than this many times the frames' median disagreement are rejected
        unbaked: a texture that does not belong to its mesh (a volumetric video frame decoded wrong)
        or a fit on the wrong part of the scan. Not in the paper, whose κ alone passes such a frame
        (κ measures where the scan is, not what colour it has). 0 = off; needs the colour rounds.
    interior_visibility: rest-pose visibility below which a texel counts as interior (the split is
        sharp: 4.07 % of anny's texels below 0.02, 4.12 % below 0.1).
    texture_float16: store the texture as float16 (half the disk space).
    device: where the ray stages run (registration and texel rays, visibility, colour sampling):
        "cpu" or "cuda" / "cuda:N" (a GPU through NVIDIA Warp's mesh BVH, ``uvatar[kernels]``); the
        other stages follow ``torch_stages``. Same maps within float32 round-off.
    torch_stages: where the rest of a frame runs: the inpainting (a layered Telea march), the
        registration's normals, smoothing and solves, the pose refinement's and colour rounds' nearest
        samples, normal equations and stencil rays, the texel rays' set-up and choice, the visibility
        rays' set-up and the texture lookups. "auto" (their torch twins on ``device`` when it is CUDA,
        the numpy / OpenCV / SciPy reference on the CPU), "on" (the torch twins on ``device``, CPU
        tensors on the CPU: what CI checks them with; slow there: a dense Cholesky of the body's
        system) or "off" (the reference everywhere). Same maps on the matched texels within float
        round-off; inpainted texels (kappa 0) within a few percent. :meth:`torch_device`.
    ray_backend: "auto" (Embree on the CPU, Warp on CUDA), "embree" or "warp" (Warp also runs on
        the CPU, single-threaded and ~3x slower than Embree: for parity checks); checked by
        :func:`uvatar.geometry.ray_backends.make_caster`.
    scan_cache_mb: scans (with their ray and k-d tree structures) kept in memory per worker process
        between the colour rounds and the bake, so a frame's scan is read and prepared once instead
        of once per round (0 = read every time; results are the same either way).
    frames_in_flight: with the torch stages on CUDA, how many frames' pose refinements and colour
        rounds one process runs at once, each on its own CUDA stream (:mod:`.refine_in_flight`: one
        refinement's small launches leave most of a GPU idle); 1 = one at a time. The same fits either
        way; ignored on the CPU.
    write_behind: in a bake of one process (``--workers 1``), write each frame (its maps and preview)
        on a thread while the next frame bakes, so the device, or the core, need not wait for the
        compression (a 1024² frame: ~0.5 s); False writes each frame before the next begins. The same
        files either way; a frame's record in ``dataset.json`` follows once its files are on disk.
    registration: :class:`RegistrationConfig`; pose_refine: :class:`PoseRefineConfig`.
    """

    texels: int = 1024
    refine_pose: bool = True
    register: bool = True
    polarity_rule: bool = True
    polarity_ratio: float = 2.0
    max_match_distance: float | None = 0.1
    ray_epsilon: float = 1e-4
    visibility_rays: int = 16
    visibility_stratified: bool = True
    distance_clip: float = 1 / 50
    inpaint_radius: int = 3
    inpaint_band: int | None = 8
    inpaint_gutter: int | None = 4
    reject_kappa: float = 130 / 255
    reject_colour_ratio: float = 4.0
    interior_visibility: float = 0.02
    texture_float16: bool = True
    device: str = "cpu"
    torch_stages: str = "auto"
    ray_backend: str = "auto"
    scan_cache_mb: int = 2048
    frames_in_flight: int = 4
    write_behind: bool = True
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    pose_refine: PoseRefineConfig = field(default_factory=PoseRefineConfig)

    def __post_init__(self) -> None:
        checks = [(self.texels >= 1, "texels must be >= 1"),
                  (self.visibility_rays >= 1, "visibility_rays must be >= 1"),
                  (self.polarity_ratio >= 1, "polarity_ratio must be >= 1 (a positive match at most this many times farther)"),
                  (self.distance_clip > 0, "distance_clip must be > 0"),
                  (self.inpaint_radius >= 0, "inpaint_radius must be >= 0"),
                  (self.inpaint_gutter is None or self.inpaint_gutter >= 0, "inpaint_gutter must be >= 0"),
                  (0.0 <= self.reject_kappa <= 1.0, "reject_kappa must be in [0, 1]"),
                  (self.reject_colour_ratio == 0 or self.reject_colour_ratio >= 1,
                   "reject_colour_ratio must be 0 (off) or >= 1"),
                  (0.0 <= self.interior_visibility < 1.0, "interior_visibility must be in [0, 1)"),
                  (self.max_match_distance is None or self.max_match_distance > 0, "max_match_distance must be > 0"),
                  (self.ray_epsilon >= 0, "ray_epsilon must be >= 0"),
                  (self.device == "cpu" or self.device.startswith("cuda"), "device must be cpu or cuda[:N]"),
                  (self.torch_stages in TORCH_STAGES, f"torch_stages must be one of {TORCH_STAGES}"),
                  (self.scan_cache_mb >= 0, "scan_cache_mb must be >= 0"),
                  (self.frames_in_flight >= 1, "frames_in_flight must be >= 1")]
        check_values(checks)

    @property
    def torch_device(self) -> str | None:
        """The torch device of the stages that cast no rays (``torch_stages``), or None for their
        numpy reference."""
        if self.torch_stages == "off" or (self.torch_stages == "auto" and not self.device.startswith("cuda")):
            return None
        return self.device

    @property
    def refines_across_frames(self) -> bool:
        """The bake refines its frames' poses together, with the cross-frame colour term
        (:mod:`uvatar.avh.bake.refine_together`)."""
        pr = self.pose_refine
        return bool(self.refine_pose and pr.photometric_radii and pr.photometric_weight > 0)

    def with_updates(self, **changes) -> BakeConfig:
        """A copy with top-level fields (or ``registration_<field>``, ``pose_refine_<field>``) replaced;
        None values are ignored."""
        top = {f.name for f in fields(self)}
        nested: dict[str, dict] = {"registration": {}, "pose_refine": {}}
        own = {}
        for key, value in changes.items():
            if value is None:
                continue
            prefix = next((p for p in nested if key.startswith(p + "_")), None)
            if prefix:
                nested[prefix][key[len(prefix) + 1:]] = value
            elif key in top:
                own[key] = value
            else:
                raise ValueError(f"unknown BakeConfig field {key!r}")
        for name, sub in nested.items():
            if sub:
                own[name] = replace(getattr(self, name), **sub)
        return replace(self, **own)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> BakeConfig:
        """Inverse of :meth:`to_dict` (JSON lists become tuples; unknown keys are ignored; a config
        written before ``visibility_stratified`` existed cast one shared lattice: False)."""
        nested = {"registration": RegistrationConfig, "pose_refine": PoseRefineConfig}
        known = {f.name for f in fields(cls)}
        top = {k: v for k, v in data.items() if k in known and k not in nested}
        if "visibility_rays" in top and "visibility_stratified" not in top:
            top["visibility_stratified"] = False
        for name, sub_cls in nested.items():
            sub_known = {f.name for f in fields(sub_cls)}
            top[name] = sub_cls(**{k: tuple(v) if isinstance(v, list) else v
                                   for k, v in (data.get(name) or {}).items() if k in sub_known})
        return cls(**top)
