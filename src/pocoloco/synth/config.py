"""Typed configurations and named presets.

Every long job is described by one frozen dataclass; named presets live in a
plain dict next to it (``SYNTH_PRESETS``), so ``pocoloco data synth --preset
small`` is ``SYNTH_PRESETS["small"]`` with command-line overrides applied.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from ..utils.config import Config


@dataclass(frozen=True)
class SubjectSpec:
    """One synthetic subject: a body shape and what it wears.

    garment: a kind of ``synth.garments.GARMENT_KINDS`` (``"skirt"``: LOOSE subject
    2, ``"long_shirt"``: LOOSE subject 1, ``"maxi_skirt"``, ``"dress"``,
    ``"sleeved_shirt"``, ``"wide_trousers"``) or ``"tight"`` (no simulated
    garment: the body surface stands for tight clothing, the control subject).
    phenotype: anny phenotype parameters in [0, 1] (gender 0 = male, 1 = female).
    garment_params: the garment's shape parameters (``garments.garment_parameters``
    lists them with their defaults), e.g. ``{"hem": 0.6, "flare": 0.4}``.
    """

    name: str
    garment: str
    phenotype: dict[str, float] = field(default_factory=dict)
    garment_params: dict[str, float] = field(default_factory=dict)


DEFAULT_SUBJECTS: tuple[SubjectSpec, ...] = (
    SubjectSpec("skirt", "skirt", {"gender": 1.0, "age": 0.45, "weight": 0.45, "height": 0.5}),
    SubjectSpec("shirt", "long_shirt", {"gender": 0.0, "age": 0.5, "weight": 0.5, "height": 0.55}),
    SubjectSpec("tight", "tight", {"gender": 0.6, "age": 0.4, "weight": 0.55, "height": 0.45}),
)


#: the motion kinds of ``tiny`` / ``small`` (``synth.motion.CLASSIC_KINDS``; tested equal)
CLASSIC_MOTION_KINDS: tuple[str, ...] = ("walk", "turn", "dance", "arm_swing", "squat", "kick", "spin")
#: every kind ``synth.motion`` draws (``synth.motion.MOTION_KINDS``; tested equal)
ALL_MOTION_KINDS: tuple[str, ...] = CLASSIC_MOTION_KINDS + ("reach", "crouch", "jump", "run", "bend", "turn_in_place")


@dataclass(frozen=True)
class SynthConfig(Config):
    """Settings of a synthetic capture run (``pocoloco data synth``).

    Sequences: each is one procedural motion (``synth.motion``) of
    ``frames_per_sequence`` stored frames, preceded by ``blend_frames`` that
    move the body from the rest pose into the motion and ``warmup_frames``
    of motion that let the cloth pick up momentum; neither is stored.

    Generation settings (data v4; ``CLOTH_VERSIONS["v3"]`` / ``["v2"]`` / ``["v1"]`` restore the
    earlier pipelines'):
    garment_tessellation: ``"isotropic_achiral"`` (v3: rings of ~2.2 cm / resolution edges joined as a
        checkerboard of quads with alternating diagonals, no preferred twist), ``"isotropic"`` (v2: the
        same rings zipped with diagonals that all lean one way, which makes a hanging tube twist and
        swing) or ``"grid"`` (v1: the first skirt / long_shirt grids, 72 x 36).
    cloth_self_contact: newton VBD cloth self-contact (~90 % fewer crossing
        triangles, but 2.4-3.2x the simulation time and, at its 1.6 cm reach, fast
        spins still tear the cloth: off by default; benchmarks/experiments/bench_cloth_settings.py).
    cloth_frame: ``"root"`` (simulate in a frame translating with the pelvis, the
        same physics; needed by self-contact) or ``"world"`` (``ClothSimSettings.frame``).
    cloth_substeps, cloth_iterations: VBD substeps per frame and iterations per
        substep (v1: 10 x 5; in the root frame 7 x 5 keeps the cloth out of the body
        better than 10 x 5 did in the world frame, benchmarks/experiments/bench_cloth_settings.py).
    capture_cull_hidden_faces: draw capture candidates only on faces that may be
        visible (``capture.possibly_visible_faces``).
    cloth_damping: what takes energy out of the cloth (``synth.fabric``): ``"physical"`` (v3: air
        drag, the fabric's bending and membrane damping and cloth-skin friction, per garment kind's
        fabric), ``"unsteady"`` (v4: the same and the extra drag of small oscillations,
        ``synth.aero``) or ``"none"`` (v1 / v2: no air, almost no damping). With the achiral mesh
        and ``"physical"`` a skirt on a still body settles to ~10 cm/s of small, smooth flapping
        (v2: 30-40 cm/s of swing): newton VBD keeps feeding a little energy into hanging cloth and
        steady quadratic drag vanishes for small motions; the v4 cloth's low-KC drag takes it out
        (docs/lab/synthetic-data.md, "Does the cloth come to rest?", "The drag of small oscillations").
    cloth_chebyshev_rho: Chebyshev acceleration of the VBD sweeps (``ClothSimSettings.chebyshev_rho``;
        v4: 0.9, v1 - v3: 0).
    self_intersection_every: count cloth self-intersections (crossing triangle
        pairs) on every this-many-th stored frame for the dataset card; 0 = never.

    Motions and splits:
    motion_kinds: the motion kinds sequences draw from (``synth.motion.MOTION_KINDS``);
        the default is the classic seven of ``tiny`` / ``small``.
    heldout_sequences: sequences per subject of a third split, ``heldout``: test-style
        motions (test parameter bands, mixed upper bodies) drawn from other seeds than
        ``test``, for judging a model on motions nobody developed against.
    frame_storage: how frame files store their arrays (``format.FRAME_STORAGES``):
        ``"float32"`` (exact, uncompressed) or ``"compact"`` (deflated, float16 normals and
        skinning transforms, int16 fixed-point positions within 0.1 mm: ~37 % of the bytes,
        benchmarks/bench_frame_storage.py). Readers need not know which.
    """

    subjects: tuple[SubjectSpec, ...] = DEFAULT_SUBJECTS
    train_sequences: int = 3
    test_sequences: int = 1
    frames_per_sequence: int = 80
    blend_frames: int = 12
    warmup_frames: int = 8
    fps: float = 25.0
    num_points: int = 40_000
    garment_resolution: float = 1.0
    capture_cameras: int = 24
    scanner_noise: float = 0.0
    seed: int = 0
    garment_tessellation: str = "isotropic_achiral"
    cloth_self_contact: bool = False
    cloth_frame: str = "root"
    cloth_substeps: int = 7
    cloth_iterations: int = 5
    cloth_damping: str = "unsteady"
    cloth_chebyshev_rho: float = 0.9
    capture_cull_hidden_faces: bool = True
    self_intersection_every: int = 10
    motion_kinds: tuple[str, ...] = CLASSIC_MOTION_KINDS
    heldout_sequences: int = 0
    frame_storage: str = "float32"



#: overrides that reproduce the first pipeline (``dataclasses.replace(config, **SYNTH_V1)``)
SYNTH_V1: dict = {
    "garment_tessellation": "grid",
    "cloth_self_contact": False,
    "cloth_frame": "world",
    "cloth_substeps": 10,
    "cloth_iterations": 5,
    "capture_cull_hidden_faces": False,
    "self_intersection_every": 0,
    "cloth_damping": "none",
    "cloth_chebyshev_rho": 0.0,
}


#: overrides that reproduce data v3 (steady drag only, plain sweeps: a hanging skirt keeps a ~10 cm/s
#: flapping; docs/lab/synthetic-data.md, "The drag of small oscillations")
SYNTH_V3: dict = {"cloth_damping": "physical", "cloth_chebyshev_rho": 0.0}

#: overrides that reproduce data v2 (the isotropic mesh, undamped cloth)
SYNTH_V2: dict = {**SYNTH_V3, "garment_tessellation": "isotropic", "cloth_damping": "none"}

#: the cloth of each data version, as overrides of the current defaults (v4: v3's cloth with the
#: drag of small oscillations and Chebyshev-accelerated sweeps, in which a hanging skirt comes to rest)
CLOTH_VERSIONS: dict[str, dict] = {"v4": {}, "v3": SYNTH_V3, "v2": SYNTH_V2, "v1": SYNTH_V1}

#: the data version ``SynthConfig()`` makes (its overrides in CLOTH_VERSIONS are empty)
CURRENT_CLOTH: str = next(name for name, overrides in CLOTH_VERSIONS.items() if not overrides)


def cloth_version(config: SynthConfig) -> str:
    """``"v4"`` / ``"v3"`` / ``"v2"`` / ``"v1"``: the data version whose cloth settings ``config``
    has, or ``"custom"`` when they match none (a run with individual settings changed)."""
    base = SynthConfig()
    for name in ("v4", "v3", "v2", "v1"):
        ref = dataclasses.replace(base, **CLOTH_VERSIONS[name])
        if all(getattr(config, k) == getattr(ref, k) for k in _CLOTH_FIELDS):
            return name
    return "custom"


def _phenotype(gender: float, height: float, weight: float, age: float = 0.45) -> dict[str, float]:
    return {"gender": gender, "age": age, "weight": weight, "height": height}


#: ``medium``: every loose garment kind on two bodies (sex, height, weight varied) + two tight
#: bodies; the first skirt, shirt and tight bodies are ``small``'s.
MEDIUM_SUBJECTS: tuple[SubjectSpec, ...] = (
    SubjectSpec("skirt_a", "skirt", DEFAULT_SUBJECTS[0].phenotype),
    SubjectSpec("skirt_b", "skirt", _phenotype(0.85, 0.7, 0.7, 0.6), {"hem": 0.5, "flare": 0.4}),
    SubjectSpec("maxi_a", "maxi_skirt", _phenotype(1.0, 0.35, 0.3, 0.35)),
    SubjectSpec("maxi_b", "maxi_skirt", _phenotype(0.9, 0.6, 0.6), {"hem": 0.85, "flare": 0.3}),
    SubjectSpec("dress_a", "dress", _phenotype(1.0, 0.55, 0.5, 0.4)),
    SubjectSpec("dress_b", "dress", _phenotype(0.85, 0.4, 0.7, 0.55), {"hem": 0.35}),
    SubjectSpec("shirt_a", "long_shirt", DEFAULT_SUBJECTS[1].phenotype),
    SubjectSpec("shirt_b", "long_shirt", _phenotype(0.7, 0.4, 0.35, 0.35), {"hem": 0.7}),
    SubjectSpec("sleeves_a", "sleeved_shirt", _phenotype(0.1, 0.7, 0.35, 0.4)),
    SubjectSpec("sleeves_b", "sleeved_shirt", _phenotype(0.0, 0.5, 0.7, 0.6), {"sleeve": 0.3}),
    SubjectSpec("trousers_a", "wide_trousers", _phenotype(0.7, 0.5, 0.55)),
    SubjectSpec("trousers_b", "wide_trousers", _phenotype(0.2, 0.65, 0.45, 0.5), {"length": 0.35}),
    SubjectSpec("tight_a", "tight", DEFAULT_SUBJECTS[2].phenotype),
    SubjectSpec("tight_b", "tight", _phenotype(0.0, 0.6, 0.7, 0.6)),
)

#: ``unseen``: garments and bodies no ``medium`` subject has, for fitting new outfits
UNSEEN_SUBJECTS: tuple[SubjectSpec, ...] = (
    SubjectSpec("dress_c", "dress", _phenotype(0.95, 0.45, 0.4, 0.5), {"hem": 0.6, "flare": 0.5}),
    SubjectSpec("shirt_c", "long_shirt", _phenotype(0.3, 0.55, 0.6, 0.5), {"hem": 0.9, "flare": 0.25}),
)

#: settings added to SynthConfig after datasets were generated, with the value those runs used: a
#: card's ``generation_config`` without the key was generated that way (a new field goes here)
FIELDS_ADDED_LATER: dict = {
    **SYNTH_V1,
    "cloth_damping": "none",
    "motion_kinds": CLASSIC_MOTION_KINDS,
    "heldout_sequences": 0,
    "frame_storage": "float32",
}


def config_of_card(generation_config: dict) -> SynthConfig:
    """The SynthConfig a dataset card's ``generation_config`` was generated with (keys it lacks take
    the value runs before them used, ``FIELDS_ADDED_LATER``); ValueError if it is not one."""
    try:
        return SynthConfig.from_dict({**FIELDS_ADDED_LATER, **generation_config})
    except (TypeError, KeyError, ValueError, AttributeError) as e:
        raise ValueError(f"not a synthetic dataset's generation_config ({e})") from None


#: the settings that decide how the cloth moves (compared by :func:`cloth_version`)
_CLOTH_FIELDS: tuple[str, ...] = tuple(SYNTH_V1)


SYNTH_PRESETS: dict[str, SynthConfig] = {
    # seconds: for tests and smoke runs
    "tiny": SynthConfig(
        subjects=(DEFAULT_SUBJECTS[0], DEFAULT_SUBJECTS[2]),
        train_sequences=1,
        test_sequences=1,
        frames_per_sequence=4,
        blend_frames=10,
        warmup_frames=4,
        num_points=4_000,
        capture_cameras=12,
    ),
    # minutes: the default demo dataset and the one shipped models train on
    "small": SynthConfig(),
    # <= 2 h on 2 cores: 14 subjects, all motion kinds, 960 train + 320 test + 80 held-out frames
    # each in 40-frame sequences (many short motions cover the pose space); long skirts and dresses
    # lose up to 15 % of their frames to rejection in crouches and sit-like poses, >= 800 + 200 stay
    "medium": SynthConfig(
        subjects=MEDIUM_SUBJECTS,
        train_sequences=24,
        test_sequences=8,
        heldout_sequences=2,
        frames_per_sequence=40,
        motion_kinds=ALL_MOTION_KINDS,
    ),
    # minutes: outfits and bodies ``medium`` does not have (a midi dress with a wide flare, a
    # knee-length tunic), for fitting an unseen outfit (``pocoloco fit``) to a few of its train
    # scans and scoring the fit in its test poses
    "unseen": SynthConfig(
        subjects=UNSEEN_SUBJECTS,
        train_sequences=1,
        test_sequences=2,
        frames_per_sequence=40,
        motion_kinds=ALL_MOTION_KINDS,
        seed=1,
    ),
    # LOOSE's scale (~30K train / ~10K test frames per subject): many cores
    "loose": SynthConfig(
        subjects=DEFAULT_SUBJECTS,
        train_sequences=120,
        test_sequences=40,
        frames_per_sequence=250,
    ),
}


def synth_preset(name: str) -> SynthConfig:
    """A named preset; a one-line error naming the known ones otherwise."""
    if name not in SYNTH_PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of: {', '.join(SYNTH_PRESETS)}")
    return SYNTH_PRESETS[name]
