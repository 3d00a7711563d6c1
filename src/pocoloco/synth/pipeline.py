"""The synthetic capture pipeline: body + motion + cloth simulation + virtual capture.

``synthesize(config, out)`` writes a dataset in the format of
``docs/reference/formats.md``. The unit of work is one *sequence* (a subject
performing one procedural motion):

1. generate the motion (``synth.motion``), prepend a blend from the rest pose;
2. pose the anny body for every frame (``body.AnnyBody``);
3. simulate the loose garment on it (``synth.cloth_sim``, newton VBD) — the
   result is cached in ``cloth.npz`` so a kill during step 4 does not redo it;
4. capture every stored frame as a scanner would (``synth.capture``) and write
   one ``frames/NNNNNN.npz`` per frame, atomically; frames whose cloth state was
   flagged bad (explosion, penetration) are rejected and logged, not stored;
5. write ``sequence.json`` last: its presence marks the sequence done.

A killed run resumes where it stopped: finished sequences are skipped,
already-written frames are kept and not rewritten. Sequences run in parallel
worker processes (``workers``). The dataset card (counts, normalisation,
loose-region share, penetration, timings) is written when all are done.

Shards: ``synthesize_shard(config, out, k, n)`` runs only shard k of n (a fixed,
cost-balanced share of the jobs, :func:`shard_assignment`) into the same folder,
e.g. one shard per cluster job on a shared filesystem; any number of shards may
start at once. It leaves the card "incomplete"; ``finalize_dataset`` writes it
once every sequence is done (``synth.distributed`` launches the shards). A frame is
the same bytes whichever shard or worker generates it.

Repair: a resume first checks every finished sequence byte for byte against the card
(:func:`repair_sequences`); damaged frames are generated again, to the same bytes.

Why this module is long: the pipeline of one sequence and the run around it (job list,
shards, resume, repair, the card written once at the end) share one contract, that a
frame is the same bytes however and whenever it is made; the issue that moves the
pipeline into its own package (``synth/``) splits it along that contract.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..utils.atomic import output_folder, save_npz_atomic
from ..utils.seeding import torch_threads
from .capture import LABEL_GARMENT, LABEL_NAMES
from .cloth_stats import merge_cloth_stats, summarise_cloth_stats
from .config import SubjectSpec, SynthConfig, config_of_card
from .fabric import fabric_for
from ..data.format import (
    FRAME_STORAGES,
    DatasetLayout,
    Frame,
    StoredMotion,
    SubjectAsset,
    make_card,
    read_frame,
    read_sequence_meta,
    card_from_disk,
    read_card,
    scan_frames,
    write_card,
    write_frame,
    write_motion,
    write_sequence_meta,
)
from ..data.format import write_subject as format_write_subject
from ..data.motion_window import MotionHistory, write_motion_history



@dataclass(frozen=True)
class SequenceJob:
    """One unit of work: subject ``subject`` performing motion ``index`` of ``split``."""

    subject: SubjectSpec
    split: str
    index: int

    @property
    def name(self) -> str:
        return f"{self.split}_{self.index:04d}"


def job_seed(config: SynthConfig, job: SequenceJob) -> int:
    """A stable 31-bit seed per (run seed, subject, split, sequence)."""
    key = f"{config.seed}/{job.subject.name}/{job.split}/{job.index}".encode()
    return int.from_bytes(hashlib.sha256(key).digest()[:4], "little") & 0x7FFFFFFF


def motion_split(split: str) -> str:
    """The motion style of a dataset split: held-out sequences draw test-style motions (test
    parameter bands, mixed upper bodies), from their own seeds (``job_seed`` hashes the split)."""
    return "test" if split == "heldout" else split


def list_jobs(config: SynthConfig) -> list[SequenceJob]:
    jobs = []
    for subject in config.subjects:
        counts = (("train", config.train_sequences), ("test", config.test_sequences),
                  ("heldout", config.heldout_sequences))  # fmt: skip
        for split, count in counts:
            jobs += [SequenceJob(subject, split, i) for i in range(count)]
    return jobs


#: expected cost of a garment subject's sequence relative to a tight one's (same length): cloth
#: simulation dominates (``shard_assignment``; measured in README "Generating big datasets")
CLOTH_COST = 4.0


def job_cost(job: SequenceJob) -> float:
    """Expected relative cost of a job (a run's sequences all have the same length)."""
    return 1.0 if job.subject.garment == "tight" else CLOTH_COST


def shard_assignment(config: SynthConfig, num_shards: int) -> list[list[int]]:
    """Which jobs each of ``num_shards`` shards runs: indices into ``list_jobs(config)``.

    Longest-processing-time-first greedy: the jobs, by decreasing :func:`job_cost` (ties in
    ``list_jobs`` order), each go to the shard with the least expected cost so far (ties: the
    lowest shard), so tight (cheap) subjects' sequences spread evenly over the shards. A shard's
    jobs run in ``list_jobs`` order (a subject's sequences in a row reuse its settled cloth). Depends
    only on ``config`` and ``num_shards``: every shard computes the same assignment.
    """
    if num_shards < 1:
        raise ValueError(f"num_shards must be >= 1, got {num_shards}")
    jobs = list_jobs(config)
    load = [0.0] * num_shards
    shards: list[list[int]] = [[] for _ in range(num_shards)]
    for i in sorted(range(len(jobs)), key=lambda i: -job_cost(jobs[i])):  # stable sort
        k = min(range(num_shards), key=lambda k: (load[k], k))
        shards[k].append(i)
        load[k] += job_cost(jobs[i])
    return [sorted(s) for s in shards]


def check_shard(shard: int, num_shards: int) -> None:
    """ValueError unless 1 <= shard <= num_shards."""
    if num_shards < 1 or not 1 <= shard <= num_shards:
        raise ValueError(f"shard must be K/N with 1 <= K <= N, got {shard}/{num_shards}")


def missing_jobs(config: SynthConfig, out: str | os.PathLike) -> list[SequenceJob]:
    """The jobs whose ``sequence.json`` (written last, marks a sequence done) is not in ``out`` yet."""
    layout = DatasetLayout(out)
    return [j for j in list_jobs(config) if not layout.sequence_meta_path(j.subject.name, j.split, j.name).exists()]


def _config_json(config: SynthConfig) -> dict:
    return json.loads(json.dumps(config.to_dict()))


def _is_card_temp(name: str) -> bool:
    """The card's temporary file, or a writer's lock file (``.lock``, ``.lock-shard-K-of-N``)."""
    return (name.startswith(".card.json.") and name.endswith(".tmp")) or name.startswith(".lock")


def prepare_output(config: SynthConfig, out: Path) -> None:
    """Create ``out`` or check it holds a run of the same configuration.

    Safe when several processes (shards) run it at once: the first creates ``card.json``
    (exclusively, before anything else in the folder), the others find it and check it.
    Raises ValueError when ``out`` is a non-empty folder that is not a dataset
    or a dataset generated with other settings (naming the differing keys).
    """
    if config.frame_storage not in FRAME_STORAGES:
        raise ValueError(f"frame_storage must be one of {FRAME_STORAGES}, got {config.frame_storage!r}")
    out = output_folder(out)
    layout = DatasetLayout(out)
    # listed before looking for the card: the card is created first and never removed, so other
    # entries while it is missing are not a (concurrent) run's
    entries = [p for p in out.iterdir() if not _is_card_temp(p.name)] if out.is_dir() else []
    if not layout.card_path.exists():
        if entries:
            raise ValueError(f"{out}: folder exists, is not empty and is not a pocoloco dataset")
        out.mkdir(parents=True, exist_ok=True)
        write_card(out, _base_card(config, status="incomplete"), exclusive=True)  # False: another won
    _check_card_config(config, out)


#: sequence counts a dataset can grow in (job i of a split is the same whatever the count)
_GROWABLE = ("train_sequences", "test_sequences", "heldout_sequences")


def _check_card_config(config: SynthConfig, out: Path) -> None:
    """ValueError unless ``out/card.json`` is readable and records ``config``."""
    layout = DatasetLayout(out)
    wanted = _config_json(config)
    try:
        card = json.loads(layout.card_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{layout.card_path}: unreadable dataset card ({e})") from None
    have = card.get("generation_config")
    try:  # settings added since the card was written: the value runs before them used
        have = _config_json(config_of_card(have))
    except ValueError:
        pass  # not readable as a config: the keys that differ are reported below
    if isinstance(have, dict):  # a split may grow later (more sequences of the same runs), not shrink
        for key in _GROWABLE:
            if isinstance(have.get(key), int) and have[key] > wanted[key]:
                raise ValueError(f"{out}: holds {have[key]} {key.replace('_', ' ')} per subject; a dataset can "
                                 f"grow but not shrink: ask for at least {have[key]}")  # fmt: skip
            have = {**have, key: wanted[key]}
    if have != wanted:
        keys = sorted(k for k in set(wanted) | set(have or {}) if (have or {}).get(k) != wanted.get(k))
        raise ValueError(
            f"{out}: holds a dataset generated with a different configuration "
            f"(differs in: {', '.join(keys)}); choose another --out"
        )


def add_heldout(
    out: str | os.PathLike, sequences: int, workers: int = 1, progress: Callable[[int, int], None] | None = None
) -> dict:
    """Draw (or extend) the ``heldout`` split of the synthetic dataset ``out`` with the settings it was
    generated with: ``sequences`` test-style motions per subject from their own seeds; train and test
    frames are left as they are (their sequences are complete, so nothing else runs). Returns the card."""
    out = Path(out)
    layout = DatasetLayout(out)
    if not layout.card_path.is_file():
        raise ValueError(f"{out}: no card.json (not a pocoloco dataset)")
    if sequences < 1:
        raise ValueError(f"--sequences must be >= 1, got {sequences}")
    try:
        card = json.loads(layout.card_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{layout.card_path}: unreadable dataset card ({e})") from None
    if not card.get("generation_config"):
        raise ValueError(f"{out}: not generated by `pocoloco data synth` (imported data has no motions to redraw)")
    config = dataclasses.replace(config_of_card(card["generation_config"]), heldout_sequences=sequences)
    return synthesize(config, out, workers=workers, progress=progress)


def _base_card(config: SynthConfig, status: str) -> dict:
    subjects = {
        s.name: {"garment_kind": s.garment, "phenotype": s.phenotype, "garment_params": _garment_params(s)}
        for s in config.subjects
    }
    card = make_card(
        subjects=subjects,
        generation_config=_config_json(config),
        label_names=list(LABEL_NAMES),
    )
    card["status"] = status
    card["skeleton"].update(up_axis="z", units="m", forward="-y")
    return card


def _garment_params(subject: SubjectSpec) -> dict | None:
    """The subject's garment parameters with the kind's defaults filled in (None for tight)."""
    if subject.garment == "tight":
        return None
    from .garments import garment_parameters

    return {**garment_parameters(subject.garment), **subject.garment_params}


# ---------------------------------------------------------------------------------------------
# per-process caches (a worker builds each subject's body and garment once, and settles its
# cloth once: every sequence starts from the same rest pose)
_BODIES: dict = {}
_SETTLED: dict = {}


def subject_key(subject: SubjectSpec, config: SynthConfig) -> tuple:
    """What makes a subject's body and garment: the key of the per-process caches."""
    return (subject.name, json.dumps(subject.phenotype, sort_keys=True), subject.garment, json.dumps(
        subject.garment_params, sort_keys=True), config.garment_resolution, config.garment_tessellation)  # fmt: skip


def subject_assets(subject: SubjectSpec, config: SynthConfig):
    """(AnnyBody, Garment | None) for a subject, built once per process."""
    key = subject_key(subject, config)
    if key not in _BODIES:
        from ..body import AnnyBody

        body = AnnyBody(subject.phenotype)
        garment = None
        if subject.garment != "tight":
            from .garments import make_garment

            garment = make_garment(subject.garment, body, resolution=config.garment_resolution,
                                   tessellation=config.garment_tessellation, **subject.garment_params)  # fmt: skip
        _BODIES[key] = (body, garment)
    return _BODIES[key]


def cloth_settings(config: SynthConfig, garment_kind: str = "skirt"):
    """The cloth simulation settings of a run for a garment of ``garment_kind``: the solver's, and the
    dissipation of the garment's fabric under the run's damping model (``synth.fabric``)."""
    from .cloth_sim import ClothSimSettings

    fabric = fabric_for(garment_kind, config.cloth_damping)
    return ClothSimSettings(fps=config.fps, substeps=config.cloth_substeps, iterations=config.cloth_iterations,
                            self_contact=config.cloth_self_contact, frame=config.cloth_frame,
                            tri_kd=fabric.membrane_damping, edge_kd=fabric.bend_damping, contact_mu=fabric.friction,
                            air_drag_normal=fabric.drag_normal, air_drag_tangential=fabric.drag_tangential,
                            air_drag_kc_gain=fabric.drag_kc_gain, air_drag_kc_width=fabric.drag_kc_width,
                            air_drag_kc_time=fabric.drag_kc_time, chebyshev_rho=config.cloth_chebyshev_rho)  # fmt: skip


def write_subject(config: SynthConfig, out: Path, subject: SubjectSpec) -> None:
    """subjects/<name>/subject.npz: body template, faces, UVs, garment rest mesh (atomically;
    processes writing it at once write the same bytes)."""
    path = DatasetLayout(out).subject_path(subject.name)
    if path.exists():
        return
    with torch_threads(1):  # as run_sequence: the same template bytes from any process
        body, garment = subject_assets(subject, config)
    path.parent.mkdir(parents=True, exist_ok=True)
    format_write_subject(
        path,
        SubjectAsset(
            template=body.template,
            faces=body.faces,
            uv=body.uv,
            uv_faces=body.uv_faces,
            vertex_joint=body.vertex_joint,
            phenotype=body.phenotype,
            garment_rest_vertices=None if garment is None else garment.rest_vertices,
            garment_faces=None if garment is None else garment.faces,
        ),
    )


def run_sequence(config: SynthConfig, out: Path, job: SequenceJob, progress: Callable[[int], None] | None = None) -> dict:
    """Generate (or finish) one sequence; returns its ``sequence.json`` record (bodies posed with
    one torch thread whatever the caller's setting: the same bytes from any process)."""
    with torch_threads(1):
        return _run_sequence(config, out, job, progress)


def _run_sequence(config: SynthConfig, out: Path, job: SequenceJob, progress: Callable[[int], None] | None) -> dict:
    from .capture import LABEL_BODY, CaptureMesh, CaptureSettings, capture_frame
    from .motion import generate_motion, rest_to_motion

    layout = DatasetLayout(out)
    seq_dir = layout.sequence_dir(job.subject.name, job.split, job.name)
    record_path = layout.sequence_meta_path(job.subject.name, job.split, job.name)
    if record_path.exists():
        record = read_sequence_meta(record_path)
        (seq_dir / "cloth.npz").unlink(missing_ok=True)  # left by a kill right after sequence.json
        if progress:
            progress(config.frames_per_sequence)
        return record
    seq_dir.mkdir(parents=True, exist_ok=True)
    body, garment = subject_assets(job.subject, config)
    write_subject(config, out, job.subject)  # (if not there yet)
    seed = job_seed(config, job)
    timings = {"motion": 0.0, "simulation": 0.0, "capture": 0.0, "write": 0.0}

    # 1-2. motion and posed body for every simulated frame
    t0 = time.perf_counter()
    motion = generate_motion(
        seed, config.frames_per_sequence + config.warmup_frames, split=motion_split(job.split), fps=config.fps,
        kinds=config.motion_kinds, body=body,
    )
    full = rest_to_motion(motion, config.blend_frames, body=body)
    start = full.num_frames - config.frames_per_sequence  # first stored frame
    posed = body.pose(full.joint_rotvecs, full.root_translation)
    write_motion(
        layout.motion_path(job.subject.name, job.split, job.name),
        StoredMotion(full.joint_rotvecs[start:], full.root_translation[start:]),
    )
    joints = body.pose_joints(full.joint_rotvecs) + np.asarray(full.root_translation, np.float32)[:, None]
    write_motion_history(layout.motion_history_path(job.subject.name, job.split, job.name),
                         MotionHistory(np.asarray(joints, np.float32), float(config.fps), start))  # motion windows
    timings["motion"] = time.perf_counter() - t0

    # 3. cloth simulation (cached)
    cloth_vertices, cloth_stats = None, None
    if garment is not None:
        cloth_vertices, cloth_stats, timings["simulation"] = _simulate_cached(
            body, garment, posed, seq_dir, start, cloth_settings(config, job.subject.garment),
            subject_key(job.subject, config),
            config.self_intersection_every,
        )

    # 4. capture
    settings = CaptureSettings(
        num_points=config.num_points, num_cameras=config.capture_cameras, noise_std=config.scanner_noise,
        cull_hidden_faces=config.capture_cull_hidden_faces,
    )
    body_part = body.vertex_joint[body.faces[:, 0]]
    rejected, shares, penetration = [], [], []
    for i in range(config.frames_per_sequence):
        t = start + i
        frame_path = layout.frame_path(job.subject.name, job.split, job.name, i)
        stats = cloth_stats[i] if cloth_stats is not None else None
        written = _written_labels(frame_path)
        if stats is not None and not stats["valid"]:
            rejected.append({"frame": i, "reason": stats["reason"]})
        elif written is not None:  # kept from an interrupted run (files are written atomically)
            shares.append(100.0 * float(np.mean(written == LABEL_GARMENT)))
        else:
            tc = time.perf_counter()
            meshes = [CaptureMesh(posed.vertices[t], body.faces, label=LABEL_BODY, face_part=body_part)]
            if cloth_vertices is not None:
                no_part = np.full(len(garment.faces), -1)
                meshes.append(CaptureMesh(cloth_vertices[i], garment.faces, label=LABEL_GARMENT, face_part=no_part))
            scan = capture_frame(meshes, dataclasses.replace(settings, seed=seed + t))
            tw = time.perf_counter()
            timings["capture"] += tw - tc
            write_frame(
                frame_path,
                Frame(
                    points=scan.points,
                    normals=scan.normals,
                    labels=scan.labels,
                    parts=scan.parts,
                    joints=posed.joints[t],
                    body_vertices=posed.vertices[t],
                    vtransf=posed.vtransf[t],
                    garment_vertices=None if cloth_vertices is None else cloth_vertices[i],
                    frame_index=i,
                ),
                storage=config.frame_storage,
            )
            timings["write"] += time.perf_counter() - tw
            shares.append(100.0 * float(np.mean(scan.labels == LABEL_GARMENT)))
        if stats is not None:
            penetration.append(stats)
        if progress:
            progress(1)

    record = {
        "subject": job.subject.name,
        "split": job.split,
        "name": job.name,
        "seed": seed,
        "fps": config.fps,
        "num_frames": config.frames_per_sequence,
        "num_stored": config.frames_per_sequence - len(rejected),
        "rejected_frames": rejected,
        "segments": [list(s) for s in motion.segments],
        "first_stored_motion_frame": config.warmup_frames,
        "loose_share_percent": float(np.mean(shares)) if shares else 0.0,
        "penetration": summarise_cloth_stats(penetration),
        "seconds": timings,
    }
    write_sequence_meta(record_path, record)
    (seq_dir / "cloth.npz").unlink(missing_ok=True)
    return record


def _written_labels(path: Path) -> np.ndarray | None:
    """Labels (N,) of an already-written, readable frame file, else None."""
    if not path.exists():
        return None
    try:
        return read_frame(path, keys=["labels"]).labels
    except ValueError:
        return None


def simulate_settling_once(body, garment, posed, settings, cache_key: tuple | None, judge_from: int = 0):
    """``simulate_garment``, the cloth settled on the first frame kept per process under
    ``cache_key`` (:func:`subject_key`; None: not kept) and the settings, and reused by the next
    simulation of that subject that starts on the same frame (the result is identical: the
    simulation is deterministic)."""
    from .cloth_sim import simulate_garment

    key = (cache_key, repr(settings))
    settled = _SETTLED.get(key)
    if settled is not None and not np.array_equal(settled.first_frame, posed.vertices[0]):
        settled = None
    seq = simulate_garment(body, garment, posed, settings, settled=settled, judge_from=judge_from)
    if cache_key is not None:
        _SETTLED[key] = seq.settled
    return seq


def _simulate_cached(body, garment, posed, seq_dir: Path, start: int, settings=None, cache_key=None,
                     self_intersection_every: int = 0):
    """Simulate the garment (or load the cached result). Returns stored-frame
    vertices (T, Vg, 3), per-stored-frame stats dicts and the seconds spent.
    Every ``self_intersection_every``-th stored frame (0: none) also gets its
    count of crossing garment triangle pairs (~0.05 s each for 2.6K vertices).
    The cloth settled on the first frame is reused as :func:`simulate_settling_once` says."""
    cache = seq_dir / "cloth.npz"
    if cache.exists():
        try:
            with np.load(cache) as z:
                return z["vertices"], json.loads(str(z["stats"])), float(z["seconds"])
        except Exception:  # a corrupt cache is simply recomputed
            cache.unlink(missing_ok=True)
    t0 = time.perf_counter()
    seq = simulate_settling_once(body, garment, posed, settings, cache_key, judge_from=start)
    stats = [dataclasses.asdict(s) for s in seq.stats[start:]]
    if seq.settings.self_contact:  # which frames kept self-contact (it is dropped after a tear)
        off = seq.self_contact_off_from
        for i, st in enumerate(stats):
            st["self_contact"] = off is None or start + i < off
    vertices = seq.vertices[start:].astype(np.float32)
    from .garments import self_intersections

    for i in range(0, len(stats) if self_intersection_every > 0 else 0, max(self_intersection_every, 1)):
        if np.isfinite(vertices[i]).all():
            stats[i]["self_intersections"] = self_intersections(vertices[i], garment.faces)
    seconds = time.perf_counter() - t0  # simulation and its checks
    save_npz_atomic(cache, vertices=vertices, stats=np.array(json.dumps(stats)), seconds=np.float64(seconds))
    return vertices, stats, seconds


# ---------------------------------------------------------------------------------------------
_PROGRESS_QUEUE = None  # set in each worker process by init_worker


def init_worker(parent_pid: int, queue) -> None:
    """Worker initializer: keep the progress queue, end this worker as soon as the main
    process is gone (killed with SIGKILL, say) instead of simulating on as an orphan that
    would race a resumed run for its files, and skip the interpreter's teardown when the
    pool retires it (multiprocessing has flushed its queues by then): the module finalisers
    of newton, torch and anny take ~2.5 s, which the pool's shutdown would wait for."""
    import atexit
    import sys
    import threading

    global _PROGRESS_QUEUE
    _PROGRESS_QUEUE = queue
    # registered first, so it runs after every other exit handler
    atexit.register(lambda: (sys.stdout.flush(), sys.stderr.flush(), os._exit(0)))

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _worker(config_dict: dict, out: str, job_index: int) -> dict:
    config = SynthConfig.from_dict(config_dict)
    job = list_jobs(config)[job_index]
    return run_sequence(config, Path(out), job, progress=_PROGRESS_QUEUE.put)


def synthesize(
    config: SynthConfig,
    out: str | os.PathLike,
    workers: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Generate (or resume) a dataset. Returns the final dataset card.

    progress(done_frames, total_frames) is called as frames complete.
    """
    out = Path(out)
    t0 = time.perf_counter()
    records = synthesize_shard(config, out, 1, 1, workers=workers, progress=progress)
    return finalize_card(config, out, records, wall_seconds=time.perf_counter() - t0, workers=workers)


def synthesize_shard(
    config: SynthConfig,
    out: str | os.PathLike,
    shard: int,
    num_shards: int,
    workers: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> list[dict]:
    """Generate (or resume) shard ``shard`` of ``num_shards`` (1-based, :func:`shard_assignment`)
    of a dataset into ``out``; the card is not finalised (:func:`finalize_dataset` does, once all
    shards are done). Returns the shard's sequence records in ``list_jobs`` order.

    progress(done_frames, total_frames) is called as the shard's frames complete.
    """
    check_shard(shard, num_shards)
    out = Path(out)
    prepare_output(config, out)
    indices = shard_assignment(config, num_shards)[shard - 1]
    jobs = list_jobs(config)
    repaired = set(repair_sequences(out, [jobs[i] for i in indices]))
    total = len(indices) * config.frames_per_sequence
    done = 0

    def tick(n: int) -> None:
        nonlocal done
        done += n
        if progress:
            progress(done, total)

    # a resumed run reports what it finished before in one count, before any new frame (a log's
    # time-left estimate starts from it), and reads those sequences' records here
    layout = DatasetLayout(out)
    done_before = {i: run_sequence(config, out, jobs[i]) for i in indices
                   if layout.sequence_meta_path(jobs[i].subject.name, jobs[i].split, jobs[i].name).exists()}  # fmt: skip
    if done_before:
        tick(len(done_before) * config.frames_per_sequence)
    todo = [i for i in indices if i not in done_before]
    if workers <= 1:
        records = [done_before[i] if i in done_before else run_sequence(config, out, jobs[i], progress=tick)
                   for i in indices]  # fmt: skip
    else:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        queue = ctx.Queue()  # frames done, from the workers (no Manager process to outlive us)
        with ProcessPoolExecutor(
            max_workers=workers, mp_context=ctx, initializer=init_worker, initargs=(os.getpid(), queue)
        ) as pool:
            futures = {i: pool.submit(_worker, config.to_dict(), str(out), i) for i in todo}
            pending = set(futures.values())
            while pending:
                while not queue.empty():
                    tick(queue.get())
                finished = {f for f in pending if f.done()}
                for f in finished:
                    f.result()  # raises a worker's error at once
                pending -= finished
                time.sleep(0.2)
            records = [done_before[i] if i in done_before else futures[i].result() for i in indices]  # in job order
        while not queue.empty():
            tick(queue.get())
    for subject in config.subjects:  # each sequence writes its own subject's file; the others here
        write_subject(config, out, subject)
    # sequences regenerated by a repair: their frame records are computed afresh by finalize_card
    return [{**r, "repaired": True} if DatasetLayout.sequence_key(r["subject"], r["split"], r["name"]) in repaired else r
            for r in records]  # fmt: skip


def repair_sequences(out: Path, jobs: list[SequenceJob]) -> list[str]:
    """Before a resume: every finished sequence of ``jobs`` is checked byte for byte against the
    card's records (size and CRC-32) and its ``sequence.json`` (frames it promises); a sequence with a
    missing, truncated or corrupt frame file loses those files and its ``sequence.json`` (the mark
    of a finished sequence), so the resume generates them again, with the same seeds: the same
    bytes as an undamaged run. Returns the repaired sequences' keys (a one-line warning each)."""
    layout = DatasetLayout(out)
    card = read_card(out)
    wanted = {(j.subject.name, j.split, j.name) for j in jobs
              if layout.sequence_meta_path(j.subject.name, j.split, j.name).exists()}  # fmt: skip
    if not wanted:
        return []
    subjects = sorted({s for s, _, _ in wanted})
    report = scan_frames(out, subjects=subjects, contents=True, card=card)
    damaged: dict[str, list] = {}
    for problem in report.problems:
        if problem.kind == "extra" or problem.path.name == "sequence.json":
            continue  # not a frame generation wrote (left alone), or a sequence to regenerate anyway
        seq_dir = problem.path.parent.parent
        key = (seq_dir.parent.parent.name, seq_dir.parent.name, seq_dir.name)
        if key in wanted:
            damaged.setdefault(key, []).append(problem)
    for (subject, split, seq), problems in sorted(damaged.items()):
        for problem in problems:
            problem.path.unlink(missing_ok=True)
        layout.sequence_meta_path(subject, split, seq).unlink()
        kinds = sorted({pr.kind for pr in problems})
        warnings.warn(f"{subject}/{split}/{seq}: {len(problems)} damaged frame file(s) ({', '.join(kinds)}; first "
                      f"{problems[0].path.name}): generating them again")  # fmt: skip
    return [layout.sequence_key(*k) for k in sorted(damaged)]


def finalize_dataset(
    config: SynthConfig, out: str | os.PathLike, workers: int = 1, wall_seconds: float | None = None,
    shards: int | None = None,
) -> dict:
    """Write the final card of a dataset whose sequences are all done (by shards, say), generating
    nothing. Returns the card.

    Raises ValueError when ``out`` is not a dataset of ``config`` or sequences are missing (how
    many, and the first). ``workers``, ``shards`` and ``wall_seconds`` (default: this call's) are
    recorded in the card's ``generation``.
    """
    t0 = time.perf_counter()
    out = Path(out)
    if not DatasetLayout(out).card_path.exists():
        raise ValueError(f"{out}: not a pocoloco dataset (no card.json); generate it first")
    _check_card_config(config, out)
    jobs = list_jobs(config)
    missing = missing_jobs(config, out)
    if missing:
        first = missing[0]
        raise ValueError(f"{out}: {len(missing)} of {len(jobs)} sequences are not done yet (the first: "
                         f"{first.subject.name}/{first.split}/{first.name}); finish the shards first")  # fmt: skip
    for subject in config.subjects:  # normally written by the shards already
        write_subject(config, out, subject)
    layout = DatasetLayout(out)
    records = [read_sequence_meta(layout.sequence_meta_path(j.subject.name, j.split, j.name)) for j in jobs]
    wall = time.perf_counter() - t0 if wall_seconds is None else wall_seconds
    return finalize_card(config, out, records, wall_seconds=wall, workers=workers, shards=shards)


def finalize_card(config: SynthConfig, out: Path, records: list[dict], wall_seconds: float, workers: int,
                  shards: int | None = None) -> dict:
    """Loose share, penetration and timings from the sequence records (in ``list_jobs`` order),
    then counts and normalisation (on train) recounted from disk -> card.json, written once at the
    end (any error before leaves the old card); the frames of records marked ``repaired`` are
    hashed afresh."""
    card = _base_card(config, status="complete")
    for subject in config.subjects:
        mine = [r for r in records if r["subject"] == subject.name]
        stored = [r for r in mine if r["num_stored"]]
        share = float(np.average([r["loose_share_percent"] for r in stored],
                                 weights=[r["num_stored"] for r in stored])) if stored else 0.0  # fmt: skip
        card["loose_share"][subject.name] = share / 100.0
        pens = [r["penetration"] for r in mine if r["penetration"]]
        card["subjects"][subject.name].update(
            loose_share_percent=share,
            penetration=merge_cloth_stats(pens) if pens else None,
            rejected_reasons=sorted({f["reason"] for r in mine for f in r["rejected_frames"]}),
        )
    seconds = {k: sum(r["seconds"][k] for r in records) for k in ("motion", "simulation", "capture", "write")}
    frames = sum(r["num_frames"] for r in records)
    card["generation"] = {
        "workers": workers,
        **({"shards": shards} if shards is not None else {}),
        "wall_seconds_last_run": wall_seconds,
        "cpu_seconds_per_frame": {k: v / max(frames, 1) for k, v in seconds.items()},
    }
    try:  # the records of frames already hashed are kept (their sequences were checked on resume)
        card["frame_files"] = read_card(out).get("frame_files") or {}
    except ValueError:
        card["frame_files"] = {}
    rehash = [DatasetLayout.sequence_key(r["subject"], r["split"], r["name"]) for r in records if r.get("repaired")]
    card = card_from_disk(out, card, normalise_on="train", rehash=rehash)  # nothing written yet
    if card.get("normalisation") is None:
        raise ValueError(f"{out}: no training frame survived generation (all rejected); see the sequence.json files")
    write_card(out, card)  # the one write: a failure above leaves the card as it was
    return card
