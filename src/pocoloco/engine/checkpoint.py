"""Training checkpoints: one folder per checkpoint, written atomically.

Layout of a run folder (see :mod:`pocoloco.engine.trainer`)::

    RUN_DIR/checkpoints/
        latest                  text file naming the newest complete checkpoint folder
                                (atomically replaced after that folder exists)
        step_000100/
            meta.json           format + version, model kind, preset, step, train config,
                                denoiser config, normalisation stats, world size, versions
            model.safetensors   the raw (non-EMA) weights
            ema.safetensors     the EMA weights (what sampling uses)
            training_state.pt   optimiser state, RNG states (python, numpy, torch, cuda), step
                                (``torch.save``; loaded with ``weights_only=True``)

A checkpoint folder is written under a hidden temporary name, every file fsynced, and then
renamed to ``step_XXXXXX`` (an atomic ``rename`` on POSIX), so a reader never sees a partial
checkpoint; ``latest`` is updated last, atomically (:func:`pocoloco.utils.atomic.atomic_open`).

A run killed while writing leaves a ``.tmp-step_*`` folder behind: :func:`clean_stale_temporaries`
(called when training starts) removes it. A checkpoint damaged after it was written (a truncated
weights file, a lost disk block) is skipped by :func:`load_checkpoint` when it is given a run or
checkpoints folder: it falls back to the newest intact checkpoint with a one-line
:class:`CheckpointFallbackWarning` naming the skipped one.

Public API: :func:`save_checkpoint`, :func:`load_checkpoint` -> :class:`Checkpoint`,
:func:`resolve_checkpoint`, :func:`read_meta`, :func:`export_for_sampling`,
:func:`capture_rng_state`, :func:`restore_rng_state`, :func:`clean_stale_temporaries`.

Checksums: ``meta.json`` records the size and SHA-256 of every other file of the checkpoint
(``files``) and of its own content (``meta_sha256``, over the canonical JSON without that key);
:func:`load_checkpoint` checks them, so a flipped byte anywhere is a damaged checkpoint (and the
fallback above applies). Checkpoints written before the checksums existed load unchecked.

Weights files may hold half-precision floats (``export_for_sampling(..., dtype="float16")``, how the
shipped models are stored): loading casts fp16 / bf16 tensors to float32, the models' compute dtype.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import re
import shutil
import uuid
import warnings
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pocoloco.data.dataset import Normalisation
from pocoloco.utils.atomic import atomic_open

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "Checkpoint",
    "CheckpointFallbackWarning",
    "CorruptCheckpointError",
    "WEIGHTS_DTYPES",
    "capture_rng_state",
    "check_model_kind",
    "latest_checkpoint",
    "clean_stale_temporaries",
    "checkpoint_candidates",
    "export_for_sampling",
    "load_checkpoint",
    "meta_digest",
    "one_line",
    "read_meta",
    "resolve_checkpoint",
    "restore_rng_state",
    "save_checkpoint",
]

CHECKPOINT_FORMAT = "pocoloco-checkpoint"
CHECKPOINT_VERSION = 1
META_FILE = "meta.json"
MODEL_FILE = "model.safetensors"
EMA_FILE = "ema.safetensors"
STATE_FILE = "training_state.pt"
LATEST_FILE = "latest"
#: storage dtypes of :func:`export_for_sampling` (``weights_dtype`` in its ``meta.json``); "int8":
#: matrices as int8 with one float16 scale per row, the rest float16 (:func:`quantise_int8`)
WEIGHTS_DTYPES = {"float32": torch.float32, "float16": torch.float16, "int8": torch.float16}
#: suffix of the per-row scales of an int8 tensor in a weights file
INT8_SCALE = ".int8_scale"
#: floating tensors with fewer elements stay float16 in an int8 export (biases, norms, small tables)
INT8_MIN_NUMEL = 1024
_HALF_DTYPES = (torch.float16, torch.bfloat16)  # cast to float32 when loaded
_STEP_DIR = re.compile(r"^step_(\d+)$")


class CorruptCheckpointError(ValueError):
    """A checkpoint folder whose files are missing, truncated or unreadable (a ValueError: one line,
    naming the file)."""


class CheckpointFallbackWarning(UserWarning):
    """A damaged checkpoint was skipped in favour of an older intact one."""


def _file_digest(path: Path) -> list:
    """[bytes, SHA-256 hex] of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return [path.stat().st_size, h.hexdigest()]


def meta_digest(meta: dict[str, Any]) -> str:
    """SHA-256 of a checkpoint meta's canonical JSON without its own ``meta_sha256`` (what that key holds)."""
    body = {k: v for k, v in meta.items() if k != "meta_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, allow_nan=False).encode()).hexdigest()


def _write_meta(folder: Path, meta: dict[str, Any], files: list[str]) -> None:
    """``meta.json`` with the digests of ``files`` (already written in ``folder``) and its own."""
    meta = {k: v for k, v in meta.items() if k not in ("files", "meta_sha256")}
    meta["files"] = {name: _file_digest(folder / name) for name in files}
    meta["meta_sha256"] = meta_digest(meta)
    with open(folder / META_FILE, "w", encoding="utf-8") as f:
        f.write(json.dumps(meta, indent=2, allow_nan=False) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _check_file(ckpt: Path, meta: dict[str, Any], name: str) -> None:
    """A CorruptCheckpointError if ``name`` differs from the digest ``meta.json`` records for it."""
    want = (meta.get("files") or {}).get(name)
    f = ckpt / name
    if want is None or not f.is_file():
        return  # an older checkpoint without checksums, or a missing file (reported by the reader)
    if f.stat().st_size != want[0]:
        raise CorruptCheckpointError(f"{f}: {f.stat().st_size} bytes, meta.json records {want[0]} (truncated or damaged)")
    if _file_digest(f)[1] != want[1]:
        raise CorruptCheckpointError(f"{f}: checksum mismatch (the file was damaged after it was written)")


def checkpoint_dir_name(step: int) -> str:
    """Folder name of the checkpoint at ``step`` (``step_000100``)."""
    return f"step_{int(step):06d}"


# --------------------------------------------------------------------------------------- RNG
def capture_rng_state() -> dict[str, Any]:
    """RNG states of python, numpy (legacy global), torch CPU and every CUDA device.

    Stored as plain python/torch objects so ``torch.load(weights_only=True)`` accepts them.
    """
    np_state = np.random.get_state(legacy=False)
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": {
            "bit_generator": np_state["bit_generator"],
            "key": torch.from_numpy(np.asarray(np_state["state"]["key"], dtype=np.int64)),
            "pos": int(np_state["state"]["pos"]),
            "has_gauss": int(np_state["has_gauss"]),
            "gauss": float(np_state["gauss"]),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state` (CUDA states are restored when CUDA is available)."""
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    n = state["numpy"]
    np.random.set_state({
        "bit_generator": n["bit_generator"],
        "state": {"key": n["key"].numpy().astype(np.uint32), "pos": int(n["pos"])},
        "has_gauss": int(n["has_gauss"]),
        "gauss": float(n["gauss"]),
    })  # fmt: skip
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ------------------------------------------------------------------------------------- saving
def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _cpu_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in state.items()}


def save_checkpoint(
    root: str | os.PathLike,
    step: int,
    *,
    model_kind: str,
    preset: str,
    config: dict[str, Any],
    normalisation: Normalisation,
    model_state: dict[str, torch.Tensor],
    ema_state: dict[str, torch.Tensor] | None = None,
    optimizer_state: dict[str, Any] | None = None,
    rng_state: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    keep: int | None = None,
) -> Path:
    """Write the checkpoint of ``step`` atomically into ``root/step_XXXXXX`` and point ``latest`` at it.

    Args:
        root: the checkpoints folder (``RUN_DIR/checkpoints``); created if missing.
        step: number of optimiser steps done.
        model_kind / preset: e.g. ``"pocoloco"`` / ``"small"`` (checked by :func:`load_checkpoint`).
        config: JSON-serialisable training config (``TrainConfig.to_dict()``); it must hold the
            denoiser config under ``"denoiser"`` for :func:`load_denoiser`.
        normalisation: the dataset's normalisation stats (needed to map samples to metres).
        model_state / ema_state: weights (tensors; saved as safetensors).
        optimizer_state: ``optimizer.state_dict()``; rng_state: :func:`capture_rng_state`.
        extra: more JSON-serialisable metadata for ``meta.json``.
        keep: keep only the ``keep`` newest ``step_*`` folders (None: keep all).
    Returns:
        the checkpoint folder.
    """
    from safetensors.torch import save_file

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = checkpoint_dir_name(step)
    final = root / name
    tmp = root / f".tmp-{name}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        meta = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "model_kind": model_kind,
            "preset": preset,
            "step": int(step),
            "config": config,
            "normalisation": {"mean": list(normalisation.mean), "std": normalisation.std,
                              "root_joint": normalisation.root_joint, "heading": normalisation.heading},  # fmt: skip
            "has_ema": ema_state is not None,
            "has_training_state": optimizer_state is not None,
            "torch_version": torch.__version__,
            **(extra or {}),
        }
        save_file(_cpu_state(model_state), str(tmp / MODEL_FILE), metadata={"step": str(step)})
        _fsync_file(tmp / MODEL_FILE)
        if ema_state is not None:
            save_file(_cpu_state(ema_state), str(tmp / EMA_FILE), metadata={"step": str(step)})
            _fsync_file(tmp / EMA_FILE)
        if optimizer_state is not None or rng_state is not None:
            with open(tmp / STATE_FILE, "wb") as f:
                torch.save({"step": int(step), "optimizer": optimizer_state, "rng": rng_state}, f)
                f.flush()
                os.fsync(f.fileno())
        _write_meta(tmp, meta, [n for n in (MODEL_FILE, EMA_FILE, STATE_FILE) if (tmp / n).is_file()])
        if final.exists():  # re-saving a step (e.g. after a resume): move the old one aside first
            trash = root / f".old-{name}-{uuid.uuid4().hex[:8]}"
            os.replace(final, trash)
            shutil.rmtree(trash, ignore_errors=True)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    with atomic_open(root / LATEST_FILE, "w") as f:
        f.write(name + "\n")
    if keep is not None and keep > 0:
        for old in _step_dirs(root)[:-keep]:
            if old.name != name:
                shutil.rmtree(old, ignore_errors=True)
    return final


def _step_dirs(root: Path) -> list[Path]:
    """``step_*`` folders of ``root``, oldest first."""
    found = [(int(m.group(1)), p) for p in root.iterdir() if p.is_dir() and (m := _STEP_DIR.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(root: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint in a checkpoints folder (``latest``, else the highest step), or None."""
    root = Path(root)
    if not root.is_dir():
        return None
    latest = root / LATEST_FILE
    if latest.is_file():
        cand = root / latest.read_text(encoding="utf-8").strip()
        if (cand / META_FILE).is_file():
            return cand
    dirs = [d for d in _step_dirs(root) if (d / META_FILE).is_file()]
    return dirs[-1] if dirs else None


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """Accept a checkpoint folder, a checkpoints folder or a run folder; return the checkpoint folder."""
    p = Path(path)
    if (p / META_FILE).is_file():
        return p
    for root in (p, p / "checkpoints"):
        found = latest_checkpoint(root)
        if found is not None:
            return found
    if not p.exists():
        raise ValueError(f"{p}: no such checkpoint or run folder")
    raise ValueError(f"{p}: no checkpoint found (expected {META_FILE}, a 'latest' file or step_* folders)")


# ------------------------------------------------------------------------------------ loading
@dataclass
class Checkpoint:
    """A loaded checkpoint (tensors on the CPU unless ``map_location`` said otherwise).

    Attributes:
        path: the checkpoint folder.
        step: optimiser steps done.
        model_kind / preset: what was trained (e.g. "pocoloco" / "small").
        config: the training config as a dict (``TrainConfig.from_dict`` rebuilds it).
        normalisation: the dataset normalisation the model was trained with.
        model_state: raw weights. ema_state: EMA weights or None (half-precision files load as float32).
        optimizer_state / rng_state: training state, or None if not saved / not loaded.
        meta: the whole ``meta.json``.
    """

    path: Path
    step: int
    model_kind: str
    preset: str
    config: dict[str, Any]
    normalisation: Normalisation
    model_state: dict[str, torch.Tensor]
    ema_state: dict[str, torch.Tensor] | None
    optimizer_state: dict[str, Any] | None = None
    rng_state: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)


def read_meta(path: str | os.PathLike) -> dict[str, Any]:
    """The ``meta.json`` of a checkpoint folder, checked (format, version, required keys)."""
    f = Path(path) / META_FILE
    try:
        meta = json.loads(f.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CorruptCheckpointError(f"{f}: missing (not a pocoloco checkpoint)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CorruptCheckpointError(f"{f}: corrupt checkpoint metadata ({type(e).__name__}: {e})") from None
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        kind = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ValueError(f"{f}: not a pocoloco checkpoint (format is {kind!r})")
    if meta.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{f}: unsupported checkpoint version {meta.get('version')!r} (expected {CHECKPOINT_VERSION})")
    for key in ("model_kind", "preset", "step", "config", "normalisation"):
        if key not in meta:
            raise CorruptCheckpointError(f"{f}: corrupt checkpoint metadata (no {key!r})")
    if "meta_sha256" in meta and meta_digest(meta) != meta["meta_sha256"]:
        raise CorruptCheckpointError(f"{f}: checksum mismatch (the metadata was damaged after it was written)")
    return meta


def one_line(e: BaseException) -> str:
    """``Type: first line of the message`` of an exception."""
    lines = str(e).strip().splitlines()
    return f"{type(e).__name__}: {lines[0]}" if lines else type(e).__name__


def _load_safetensors(f: Path, device: str | torch.device) -> dict[str, torch.Tensor]:
    """The tensors of a weights file; half-precision floats (fp16 / bf16) cast to float32, the
    models' compute dtype. A non-finite float (NaN, inf) anywhere is a :class:`CorruptCheckpointError`
    naming the tensor (a diverged run's weights, not a user's pose, are what is wrong)."""
    from safetensors.torch import load_file

    if not f.is_file():
        raise CorruptCheckpointError(f"{f}: missing from the checkpoint")
    try:
        state = load_file(str(f), device=str(device))
    except Exception as e:  # safetensors raises its own error types for truncated / garbage files
        raise CorruptCheckpointError(f"{f}: corrupt weights file ({one_line(e)})") from None
    scales = {k[: -len(INT8_SCALE)]: state.pop(k) for k in [k for k in state if k.endswith(INT8_SCALE)]}
    for k, scale in scales.items():  # int8 rows back to float32 (export_for_sampling(dtype="int8"))
        if k not in state or state[k].dtype != torch.int8 or tuple(scale.shape) != tuple(state[k].shape[:-1]):
            raise CorruptCheckpointError(f"{f}: corrupt weights file (int8 scales of {k!r} do not match it)")
        state[k] = dequantise_int8(state[k], scale)
    for k, v in state.items():
        if v.dtype in _HALF_DTYPES:
            state[k] = v = v.float()
        elif v.dtype == torch.int32:  # an int64 buffer stored narrow (export_for_sampling)
            state[k] = v = v.long()
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):  # NaN weights: say so here, not later
            bad = int((~torch.isfinite(v)).sum())
            raise CorruptCheckpointError(f"{f}: corrupt weights file ({k!r} holds {bad} non-finite "
                                         f"value{'s' if bad > 1 else ''}: NaN or infinite)")  # fmt: skip
    return state


def load_checkpoint(
    path: str | os.PathLike,
    expect_model: str | None = "pocoloco",
    expect_preset: str | None = None,
    map_location: str | torch.device = "cpu",
    training_state: bool = True,
) -> Checkpoint:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: a checkpoint folder, or a checkpoints folder or run folder: then the newest intact
            checkpoint (a damaged newer one is skipped with a :class:`CheckpointFallbackWarning`).
        expect_model / expect_preset: raise if the checkpoint is of another model / preset
            (None: accept any).
        map_location: device for the tensors.
        training_state: also load the optimiser and RNG states (needed to resume).
    Raises:
        ValueError (one line, naming the file): missing or corrupt files, wrong model or preset.
    """
    p = Path(path)
    if (p / META_FILE).is_file() or not p.exists():  # one checkpoint asked for by name: no fallback
        return _load_one(resolve_checkpoint(p), expect_model, expect_preset, map_location, training_state)
    candidates = checkpoint_candidates(p)
    if not candidates:
        resolve_checkpoint(p)  # raises the one-line "no checkpoint found"
    skipped: list[str] = []
    for ckpt in candidates:
        try:
            loaded = _load_one(ckpt, expect_model, expect_preset, map_location, training_state)
        except CorruptCheckpointError as e:
            skipped.append(f"{ckpt.name} ({e})")
            continue
        if skipped:
            warnings.warn(f"skipped damaged checkpoint {skipped[0]}" + (f" and {len(skipped) - 1} more" if len(skipped) > 1
                          else "") + f"; using {ckpt}", CheckpointFallbackWarning, stacklevel=2)  # fmt: skip
        return loaded
    raise CorruptCheckpointError(f"{p}: every checkpoint is damaged; the newest: {skipped[0]}")


def checkpoint_candidates(path: str | os.PathLike) -> list[Path]:
    """Checkpoint folders of a run or checkpoints folder, newest first (the one ``latest`` names first)."""
    p = Path(path)
    for root in (p, p / "checkpoints"):
        if not root.is_dir():
            continue
        dirs = [d for d in reversed(_step_dirs(root)) if (d / META_FILE).is_file()]
        first = latest_checkpoint(root)
        if first is not None:
            dirs = [first] + [d for d in dirs if d != first]
        if dirs:
            return dirs
    return []


def clean_stale_temporaries(root: str | os.PathLike) -> list[Path]:
    """Remove the ``.tmp-step_*`` / ``.old-step_*`` folders an interrupted :func:`save_checkpoint`
    left in the checkpoints folder ``root``; returns what was removed."""
    root = Path(root)
    if not root.is_dir():
        return []
    stale = [d for d in root.iterdir() if d.is_dir() and d.name.startswith((".tmp-step_", ".old-step_"))]
    for d in stale:
        shutil.rmtree(d, ignore_errors=True)
    return stale


def check_model_kind(ckpt: str | os.PathLike, kind: str, expected: str, hint: str = "") -> None:
    """One-line error when the checkpoint folder ``ckpt`` holds model ``kind``, not ``expected``;
    ``hint`` (the option it came from, say) is appended in parentheses."""
    if kind != expected:
        more = f" ({hint})" if hint else ""
        raise ValueError(f"{Path(ckpt) / META_FILE}: checkpoint is of model {kind!r}, expected {expected!r}{more}")


def _load_one(ckpt: Path, expect_model: str | None, expect_preset: str | None, map_location,
              training_state: bool) -> Checkpoint:  # fmt: skip
    meta = read_meta(ckpt)
    if expect_model is not None:
        check_model_kind(ckpt, meta["model_kind"], expect_model)
    if expect_preset is not None and meta["preset"] != expect_preset:
        raise ValueError(f"{ckpt / META_FILE}: checkpoint is of preset {meta['preset']!r}, expected {expect_preset!r}")
    try:
        norm = meta["normalisation"]
        normalisation = Normalisation(mean=tuple(float(x) for x in norm["mean"]), std=float(norm["std"]),
                                      root_joint=int(norm.get("root_joint", 0)),
                                      heading=bool(norm.get("heading", False)))  # fmt: skip
    except (KeyError, TypeError, ValueError) as e:
        raise CorruptCheckpointError(f"{ckpt / META_FILE}: corrupt normalisation stats ({e})") from None
    _check_file(ckpt, meta, MODEL_FILE)
    model_state = _load_safetensors(ckpt / MODEL_FILE, map_location)
    if meta.get("has_ema", False):
        _check_file(ckpt, meta, EMA_FILE)
    ema_state = _load_safetensors(ckpt / EMA_FILE, map_location) if meta.get("has_ema", False) else None
    optimizer_state = rng_state = None
    if training_state and meta.get("has_training_state", False):
        f = ckpt / STATE_FILE
        if not f.is_file():
            raise CorruptCheckpointError(f"{f}: missing from the checkpoint")
        _check_file(ckpt, meta, STATE_FILE)
        try:
            state = torch.load(f, map_location=map_location, weights_only=True)
        except Exception as e:
            raise CorruptCheckpointError(f"{f}: corrupt training state ({one_line(e)})") from None
        if not isinstance(state, dict) or int(state.get("step", -1)) != int(meta["step"]):
            got = state.get("step") if isinstance(state, dict) else None
            raise CorruptCheckpointError(f"{f}: training state does not match {META_FILE} (step {got} vs {meta['step']})")
        optimizer_state, rng_state = state.get("optimizer"), state.get("rng")
    return Checkpoint(
        path=ckpt, step=int(meta["step"]), model_kind=meta["model_kind"], preset=meta["preset"],
        config=meta["config"], normalisation=normalisation, model_state=model_state, ema_state=ema_state,
        optimizer_state=optimizer_state, rng_state=rng_state, meta=meta,
    )  # fmt: skip


def export_for_sampling(path: str | os.PathLike | Checkpoint, out: str | os.PathLike, use_ema: bool = True,
                        dtype: str = "float32", keep_float32: Collection[str] = (),
                        extra_meta: Mapping[str, Any] | None = None) -> Path:
    """Write a small sampling-only copy of a checkpoint: ``meta.json`` + one ``model.safetensors``.

    The weights are the EMA weights (``use_ema``, if the checkpoint has them) or the raw ones; no
    optimiser or RNG state, so it cannot be resumed. Written atomically (temporary folder, rename).
    This is how the models shipped in ``pocoloco/assets`` were made. Returns ``out``.

    path: a checkpoint (file, folder or run) or one already loaded (:func:`load_checkpoint`).

    dtype: storage dtype of the floating tensors, ``"float32"``, ``"float16"`` (half the bytes;
        loading casts back to float32; with ``"float16"``, int64 buffers whose values fit are stored
        as int32 too, e.g. a body's faces, and loading casts them back) or ``"int8"`` (a quarter:
        matrices of >= 1,024 values as per-row int8, :func:`quantise_int8`, the rest as float16).
        Recorded in ``meta.json``
        as ``weights_dtype``. A value beyond float16's range (65504) is a one-line ValueError.
    keep_float32: tensors stored in float32 whatever ``dtype`` (a model's geometry buffers: a
        template's vertices in metres lose ~0.5 mm to float16, which moves every output point).
    extra_meta: entries added to ``meta.json`` (e.g. a distilled model's ``polish`` link).
    """
    from safetensors.torch import save_file

    if dtype not in WEIGHTS_DTYPES:
        raise ValueError(f"weights dtype {dtype!r}: choose one of {', '.join(WEIGHTS_DTYPES)}")
    ck = path if isinstance(path, Checkpoint) else load_checkpoint(path, expect_model=None, training_state=False)
    state = ck.ema_state if (use_ema and ck.ema_state is not None) else ck.model_state
    if dtype != "float32":
        keep = set(keep_float32)
        if dtype == "int8":
            state = _quantised(state, keep)
        state = {k: v if k in keep or v.dtype == torch.int8 else _cast_finite(k, v, WEIGHTS_DTYPES[dtype], ck.path)
                 for k, v in state.items()}  # fmt: skip
        state = {k: _narrow_int(v) for k, v in state.items()}
    meta = dict(ck.meta)
    meta.update(has_ema=False, has_training_state=False, exported_from=str(ck.path),
                weights="ema" if (use_ema and ck.ema_state is not None) else "raw", weights_dtype=dtype)  # fmt: skip
    meta.update(extra_meta or {})
    out = Path(out)
    if out.exists():
        raise ValueError(f"{out}: already exists")
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        save_file({k: v.contiguous() for k, v in state.items()}, str(tmp / MODEL_FILE))
        os.chmod(tmp / MODEL_FILE, 0o644)  # shipped with the package: readable by every user
        _write_meta(tmp, meta, [MODEL_FILE])
        os.chmod(tmp / META_FILE, 0o644)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def quantise_int8(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric per-row int8 of a float tensor (..., D): ``q = round(v / s)``, ``s = max|row| / 127``
    per row of the last axis (a linear layer's output channel, a vertex's code); returns (q int8
    (..., D), s float16 (...)). The round-off is at most s / 2 per value (:func:`dequantise_int8`)."""
    rows = v.float()
    scale = (rows.abs().amax(-1) / 127.0).half()
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))  # an all-zero row (or one below fp16's range)
    q = torch.round(rows / scale.float().unsqueeze(-1)).clamp(-127, 127).to(torch.int8)
    return q, scale


def dequantise_int8(q: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """float32 ``q * s`` (the inverse of :func:`quantise_int8` up to its round-off)."""
    return q.float() * scale.float().unsqueeze(-1)


def _quantised(state: dict[str, torch.Tensor], keep: set[str]) -> dict[str, torch.Tensor]:
    """An int8 export's tensors: floating matrices of >= INT8_MIN_NUMEL elements as int8 + scales."""
    out = {}
    for k, v in state.items():
        if k not in keep and v.is_floating_point() and v.ndim >= 2 and v.numel() >= INT8_MIN_NUMEL:
            out[k], out[k + INT8_SCALE] = quantise_int8(v)
        else:
            out[k] = v
    return out


def _narrow_int(v: torch.Tensor) -> torch.Tensor:
    """An int64 tensor whose values fit in int32 as int32 (loading casts it back); others as they are."""
    if v.dtype != torch.int64 or (v.numel() and (int(v.max()) > 2**31 - 1 or int(v.min()) < -(2**31))):
        return v
    return v.to(torch.int32)


def _cast_finite(name: str, v: torch.Tensor, dtype: torch.dtype, source: Path) -> torch.Tensor:
    """Floating ``v`` cast to ``dtype`` (others as they are); a finite value that overflows is a ValueError."""
    if not v.is_floating_point():
        return v
    cast = v.to(dtype)
    if not bool(torch.isfinite(cast).all()) and bool(torch.isfinite(v).all()):
        raise ValueError(f"{source}: tensor {name!r} does not fit in {dtype} (max |value| "
                         f"{float(v.abs().max()):.4g}); export it as float32")  # fmt: skip
    return cast
