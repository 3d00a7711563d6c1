"""Integrity of a dataset's frame files against its card: :func:`check_frames` (what training and
evaluation call) compares the frame files present with the card's records and each
``sequence.json`` using only directory listings and file sizes; :func:`verify_dataset`
(``pocoloco data verify``) also reads every byte. Cards written before ``frame_files`` existed stay
valid: their frames are "not recorded", checked against ``sequence.json`` and by reading them, never
reported as corrupt for lacking a record."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .card import (
    SPLITS,
    DatasetLayout,
    check_split,
    file_crc32,
    is_frame_record,
    npz_directory_error,
    read_card,
    write_card,
)
from .frame import FRAME_FILE_NAME, read_frame, read_sequence_meta


# --------------------------------------------------------------------------- integrity
#: What can be wrong with a frame file, in the order reports list them.
PROBLEM_KINDS: tuple[str, ...] = ("missing", "extra", "size", "checksum", "unreadable")


@dataclass(frozen=True)
class FrameProblem:
    """One frame file (or ``sequence.json``) that disagrees with what the dataset says about it.

    kind: ``missing`` (the card's records or ``sequence.json`` expect it, it is not on disk),
    ``extra`` (on disk, expected by neither), ``size`` (its size differs from the card's record:
    truncated or overwritten), ``checksum`` (same size, different CRC-32: corrupt),
    ``unreadable`` (not a readable frame npz, or a malformed ``sequence.json``).
    path: the file. detail: one line.
    """

    kind: str
    path: Path
    detail: str

    def __str__(self) -> str:
        return f"{self.path}: {self.detail}"


@dataclass
class FrameReport:
    """What :func:`scan_frames` found.

    frames: frame files examined (present on disk). recorded: those the card records (size and
    CRC-32); the others were checked against ``sequence.json`` and by reading them only.
    card_records: whether the card has ``frame_files`` at all (False: a dataset written before
    them). contents: whether file contents were checked (checksums, full reads) or only sizes.
    problems: sorted by path. records: with ``contents``, ``frame_files`` as computed from disk.
    """

    root: Path
    card_records: bool
    contents: bool
    frames: int = 0
    recorded: int = 0
    problems: list[FrameProblem] = field(default_factory=list)
    records: dict[str, dict[str, list]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def kinds(self) -> dict[str, int]:
        """Number of problems of each kind (kinds with none left out), in ``PROBLEM_KINDS`` order."""
        out = {k: sum(p.kind == k for p in self.problems) for k in PROBLEM_KINDS}
        return {k: n for k, n in out.items() if n}

    def summary(self) -> str:
        """One line: ``2 bad frame files (1 missing, 1 size); first: <problem>`` or ``960 frame files OK``."""
        if self.ok:
            return f"{self.frames} frame files OK"
        kinds = ", ".join(f"{n} {k}" for k, n in self.kinds().items())
        n = len(self.problems)
        return f"{n} bad frame file{'s' if n != 1 else ''} ({kinds}); first: {self.problems[0]}"


def _expected_by_meta(layout: DatasetLayout, subject: str, split: str, seq: str,
                      problems: list[FrameProblem]) -> set[int] | None:  # fmt: skip
    """Frame indices ``sequence.json`` promises (``range(num_frames)`` minus rejected frames); None
    without a ``sequence.json`` (a sequence being generated); a malformed one is a problem."""
    meta_path = layout.sequence_meta_path(subject, split, seq)
    if not meta_path.is_file():
        return None
    try:
        meta = read_sequence_meta(meta_path)
    except ValueError as e:
        problems.append(FrameProblem("unreadable", meta_path, str(e).split(": ", 1)[-1]))
        return None
    rejected = {r.get("frame") for r in meta.get("rejected_frames", []) if isinstance(r, dict)}
    return set(range(meta["num_frames"])) - rejected


def _sequences_to_scan(layout: DatasetLayout, card: Mapping[str, Any], splits: Sequence[str],
                       subjects: Sequence[str] | None) -> list[tuple[str, str, str]]:  # fmt: skip
    """(subject, split, sequence) on disk or in the card's records, sorted."""
    files = card.get("frame_files") or {}
    chosen = sorted(set(card["subjects"]) | set(layout.subjects())) if subjects is None else sorted(subjects)
    out = set()
    for s in chosen:
        for split in splits:
            out |= {(s, split, q) for q in layout.sequences(s, split)}
            out |= {(s, split, k.split("/", 2)[2]) for k in files if k.startswith(f"{s}/{split}/")}
    return sorted(out)


def scan_frames(
    root: str | os.PathLike,
    *,
    splits: Sequence[str] = SPLITS,
    subjects: Sequence[str] | None = None,
    contents: bool = False,
    card: Mapping[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> FrameReport:
    """Compare the frame files of ``splits`` (of ``subjects``; None: every subject of the card or
    on disk) with the card's ``frame_files`` records and each ``sequence.json``.

    Always: a frame file the card records, or ``sequence.json`` promises (``range(num_frames)``
    minus its rejected frames), but absent is ``missing``; one present that either of them does
    not list is ``extra``; a recorded one of another size is ``size``. Without ``contents``
    (cheap: listings and sizes) a frame the card does not record is checked to open as a zip
    archive (its central directory, at the end: truncation shows). With ``contents`` every byte
    is read: recorded frames must match their CRC-32, the others must pass :func:`read_frame`,
    and ``report.records`` holds the ``frame_files`` of what is on disk.
    ``progress(done, total)`` is called after each frame file.
    """
    root = Path(root)
    card = read_card(root) if card is None else card
    for split in splits:
        check_split(split)
    layout = DatasetLayout(root)
    files = card.get("frame_files")
    report = FrameReport(root, card_records=files is not None, contents=contents)
    plan = []
    for s, split, seq in _sequences_to_scan(layout, card, splits, subjects):
        key = layout.sequence_key(s, split, seq)
        recorded = None
        if files is not None:
            recorded = {}
            for name, rec in files.get(key, {}).items():
                m = FRAME_FILE_NAME.match(name)
                if m is None or not is_frame_record(rec):
                    raise ValueError(f"{layout.card_path}: malformed frame_files record {key}/{name}: {rec!r}")
                recorded[int(m.group(1))] = rec
        plan.append((s, split, seq, key, recorded, layout.frame_indices(s, split, seq)))
    total = sum(len(present) for *_, present in plan)
    done = 0
    for s, split, seq, key, recorded, present_list in plan:
        problems: list[FrameProblem] = []
        present = set(present_list)
        by_meta = _expected_by_meta(layout, s, split, seq, problems)
        for i in sorted((by_meta or set()) | set(recorded or {})):
            if i not in present:
                why = "card.json records it" if recorded and i in recorded else "sequence.json lists it"
                problems.append(FrameProblem("missing", layout.frame_path(s, split, seq, i), f"missing ({why})"))
        records = {}
        for i in present_list:
            p = layout.frame_path(s, split, seq, i)
            done += 1
            report.frames += 1
            if recorded is not None and i not in recorded:
                problems.append(FrameProblem("extra", p, "not recorded in card.json"))
            elif by_meta is not None and i not in by_meta:
                problems.append(FrameProblem("extra", p, "not one of sequence.json's frames (rejected or beyond "
                                                         "num_frames)"))  # fmt: skip
            else:
                problem, record = _check_frame_file(p, recorded.get(i) if recorded else None, contents)
                report.recorded += bool(recorded and i in recorded)
                if problem is not None:
                    problems.append(problem)
                elif record is not None:
                    records[p.name] = record
            if progress is not None:
                progress(done, total)
        if contents:
            report.records[key] = records
        report.problems += sorted(problems, key=lambda q: str(q.path))
    return report


def _check_frame_file(path: Path, rec: list | None, contents: bool) -> tuple[FrameProblem | None, list | None]:
    """(problem or None, the file's [bytes, crc32] when ``contents``) for one present frame file."""
    size = path.stat().st_size
    if rec is not None and size != rec[0]:
        what = "truncated" if size < rec[0] else "overwritten"
        return FrameProblem("size", path, f"{size} bytes, card.json records {rec[0]} ({what})"), None
    if not contents:
        error = None if rec is not None else npz_directory_error(path)
        return (FrameProblem("unreadable", path, error) if error else None), None
    crc = file_crc32(path)
    if rec is not None:
        if crc != rec[1]:
            return FrameProblem("checksum", path, f"CRC-32 {crc}, card.json records {rec[1]} (corrupt)"), None
        return None, [size, crc]
    try:
        read_frame(path)
    except ValueError as e:
        return FrameProblem("unreadable", path, str(e).split(": ", 1)[-1]), None
    return None, [size, crc]


def check_frames(
    root: str | os.PathLike,
    *,
    splits: Sequence[str] = SPLITS,
    subjects: Sequence[str] | None = None,
    card: Mapping[str, Any] | None = None,
) -> FrameReport:
    """The cheap :func:`scan_frames` (listings and sizes) training and evaluation run first; any
    missing, extra, truncated or unreadable frame raises one line naming the first one."""
    report = scan_frames(root, splits=splits, subjects=subjects, card=card)
    if not report.ok:
        raise ValueError(f"{report.summary()}; run `pocoloco data verify {os.fspath(root)}` for the full list")
    return report


def verify_dataset(
    root: str | os.PathLike, *, record: bool = False, progress: Callable[[int, int], None] | None = None
) -> FrameReport:
    """Every frame file of the dataset at ``root`` checked, reading every byte (:func:`scan_frames`
    with ``contents``): recorded frames against their CRC-32, unrecorded ones by :func:`read_frame`.

    ``record``: when nothing is wrong and the card has no ``frame_files`` (a dataset written before
    them), write the sizes and checksums just computed into the card (nothing else changes).
    """
    card = read_card(root)
    report = scan_frames(root, contents=True, card=card, progress=progress)
    if record and report.ok and not report.card_records:
        write_card(root, {**card, "frame_files": report.records})
    return report
