"""The pocoloco on-disk dataset format (``"pocoloco-dataset"``, version 1).

One folder per dataset; the full specification is ``docs/reference/formats.md``.
In short::

    DATASET/
      card.json                                     # what the dataset is (see make_card)
      subjects/<subject>/subject.npz                # body template, faces, UVs, garment rest mesh
      subjects/<subject>/<split>/<sequence>/sequence.json
      subjects/<subject>/<split>/<sequence>/motion.npz
      subjects/<subject>/<split>/<sequence>/motion_history.npz   # optional: the motion before frame 0 too
      subjects/<subject>/<split>/<sequence>/frames/000123.npz

Every file is written atomically (temp file + ``os.replace``), so an
interrupted generator never leaves a half-written frame behind.

The format lives in three modules, one job each, and this one gathers their public names (what
the rest of the package imports as ``format``):

* :mod:`pocoloco.data.frame`: the frame schema and labels, frame storage (float32 / compact), the
  validating frame reader and the atomic writers, and the subject / motion / sequence files;
* :mod:`pocoloco.data.card`: the folder layout (:class:`DatasetLayout`), the card, normalisation,
  pose coverage, and the per-frame size + CRC-32 records the card keeps;
* :mod:`pocoloco.data.verify`: the checks that compare the card with the files
  (:func:`check_frames`, :func:`verify_dataset`).
"""

from __future__ import annotations

from .card import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SPLITS,
    DatasetLayout,
    card_from_disk,
    compute_normalisation,
    file_crc32,
    frame_record,
    make_card,
    pose_coverage,
    read_card,
    refresh_card,
    write_card,
)
from .frame import (
    COMPACT_MAX_ERROR,
    FRAME_KEYS,
    FRAME_STORAGES,
    LABEL_BODY,
    LABEL_GARMENT,
    LABEL_NAMES,
    LABEL_UNKNOWN,
    OPTIONAL_FRAME_KEYS,
    REQUIRED_FRAME_KEYS,
    Frame,
    StoredMotion,
    SubjectAsset,
    encode_compact,
    frame_storage,
    load_npz,
    read_frame,
    read_motion,
    read_sequence_meta,
    read_subject,
    write_frame,
    write_motion,
    write_sequence_meta,
    write_subject,
)
from .verify import PROBLEM_KINDS, FrameProblem, FrameReport, check_frames, scan_frames, verify_dataset

__all__ = [
    "FORMAT_NAME", "FORMAT_VERSION", "SPLITS", "LABEL_BODY", "LABEL_GARMENT", "LABEL_NAMES", "LABEL_UNKNOWN",
    "FRAME_KEYS", "REQUIRED_FRAME_KEYS", "OPTIONAL_FRAME_KEYS", "FRAME_STORAGES", "COMPACT_MAX_ERROR", "Frame",
    "write_frame", "read_frame", "load_npz", "encode_compact", "frame_storage", "DatasetLayout", "make_card",
    "read_card", "write_card", "compute_normalisation", "refresh_card", "card_from_disk", "pose_coverage",
    "SubjectAsset", "write_subject", "read_subject", "StoredMotion", "write_motion", "read_motion",
    "write_sequence_meta", "read_sequence_meta",
    "PROBLEM_KINDS", "FrameProblem", "FrameReport", "file_crc32", "frame_record", "scan_frames", "check_frames",
    "verify_dataset",
]  # fmt: skip
