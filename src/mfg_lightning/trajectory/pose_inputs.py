"""The inputs of a pose-file evaluation (``mfg-eval-poses``): which methods and sequences, their
files read, and their poses matched to the ground truth's.

``--gt`` is a pose file or a directory of ``<seq>.txt`` files (KITTI's ``poses/``); each
``--pred`` is ``name=<file|dir>`` (or just ``<file|dir>``, named after it). A sequence asked for
by number finds its zero-padded file (``--seqs 9`` reads ``09.txt``, kitti-odom-eval's spelling)
and is named after the file. Every problem is a :class:`~.pose_io.PoseFileError` naming the file
and line, or an :class:`InputError` for arguments that do not fit together. numpy only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mfg_lightning.trajectory.association import MatchOptions, PoseMatch, SequenceMatcher
from mfg_lightning.trajectory.pose_io import PoseFile, PoseFileError, read_poses

__all__ = [
    "InputError",
    "Inputs",
    "check_out",
    "parse_method",
    "read_inputs",
    "sequence_file",
]


class InputError(ValueError):
    """A problem with the command's arguments that is not inside one file (one line)."""


def sequence_file(directory: Path, seq: str) -> Path:
    """``directory/<seq>.txt``, or for a number the file whose stem is that number zero-padded
    (``9`` → ``09.txt``); the plain name when neither exists (the caller reports it)."""
    exact = directory / f"{seq}.txt"
    if exact.is_file() or not seq.isdigit():
        return exact
    padded = [p for p in sorted(directory.glob("*.txt"))
              if p.stem.isdigit() and int(p.stem) == int(seq) and p.is_file()]  # fmt: skip
    return padded[0] if len(padded) == 1 else exact


@dataclass(frozen=True)
class Inputs:
    """The pose files to evaluate, read, matched and checked.

    Attributes:
        gt: sequence → ground-truth file, in evaluation order.
        methods: method name → sequence → its pose file (the same sequences as ``gt``).
        matches: method name → sequence → its poses matched to the ground truth's.
        sources: method name → the ``--pred`` path it came from.
        single: one unnamed ``--pred <file>`` against a ``--gt <file>`` (the flat output).
        directories: the input directories (never written into).
    """

    gt: dict[str, PoseFile]
    methods: dict[str, dict[str, PoseFile]]
    matches: dict[str, dict[str, PoseMatch]]
    sources: dict[str, Path]
    single: bool
    directories: list[Path]


def parse_method(spec: str) -> tuple[str | None, Path]:
    """``name=<path>`` → ``(name, path)``; a bare ``<path>`` → ``(None, path)``.

    A ``name`` is what precedes the first ``=``, when that is non-empty and holds no path
    separator (so a path that contains ``=`` can still be given as ``./a=b.txt``).
    """
    name, sep, rest = spec.partition("=")
    if sep and name and "/" not in name and "\\" not in name and rest:
        return name, Path(rest)
    return None, Path(spec)


def _sequence_names(gt: Path, seqs: Sequence[str] | None) -> dict[str, Path]:
    """Sequence → ground-truth file: the ``<seq>.txt`` of a directory, or the one file."""
    if gt.is_dir():
        if seqs:
            return {(f := sequence_file(gt, s)).stem: f for s in seqs}
        found = {p.stem: p for p in sorted(gt.glob("*.txt")) if p.is_file()}
        if not found:
            raise InputError(f"{gt}: the ground-truth directory holds no <seq>.txt pose files")
        return found
    if seqs and [s.lstrip("0") or "0" for s in seqs] != [gt.stem.lstrip("0") or "0"]:
        raise InputError(
            f"--seqs {' '.join(seqs)}: --gt {gt} is one file (sequence {gt.stem}); give a "
            "directory of <seq>.txt files to choose sequences"
        )
    return {gt.stem: gt}


def _method_files(name: str, path: Path, sequences: dict[str, Path], gt: Path) -> dict[str, Path]:
    """Sequence → the method's file, for every evaluated sequence."""
    if path.is_dir():
        files = {}
        for seq, gt_file in sequences.items():
            candidate = sequence_file(path, seq)
            if not candidate.is_file():
                raise PoseFileError(
                    candidate,
                    1,
                    f"method {name!r} has no poses for sequence {seq} (ground truth {gt_file}); "
                    "leave the sequence out with --seqs",
                )
            files[seq] = candidate
        return files
    if len(sequences) != 1:
        raise InputError(
            f"--pred {name}={path}: a file holds one sequence but {len(sequences)} are evaluated "
            f"({', '.join(sequences)} of {gt}); give a directory of <seq>.txt files"
        )
    return {next(iter(sequences)): path}


def read_inputs(
    gt: str | Path,
    preds: Sequence[str],
    seqs: Sequence[str] | None = None,
    fmt: str = "auto",
    options: MatchOptions | None = None,
) -> Inputs:
    """Read, match and check every pose file of an evaluation (see the module docstring).

    Raises:
        PoseFileError: a file that cannot be read as a pose file, a missing sequence of a method
            (naming the file it looked for), a frame the ground truth does not have, too few
            matched poses.
        InputError: arguments that do not fit together (repeated names, a file for many
            sequences).
        ValueError: ``--gt-times`` without the times of a sequence.
    """
    gt = Path(gt)
    options = options or MatchOptions()
    sequences = _sequence_names(gt, seqs)
    named = [parse_method(spec) for spec in preds]
    sources: dict[str, Path] = {}
    for name, path in named:
        name = name or (path.stem if path.suffix else path.name) or str(path)
        if name in sources:
            raise InputError(f"--pred: two methods are named {name!r}; name them with name=<path>")
        sources[name] = path
    gt_files = {seq: read_poses(path, fmt) for seq, path in sequences.items()}
    files = {name: _method_files(name, path, sequences, gt) for name, path in sources.items()}
    single_seq = len(sequences) == 1
    matchers = {s: SequenceMatcher(s, f, options, single_seq) for s, f in gt_files.items()}
    methods: dict[str, dict[str, PoseFile]] = {}
    matches: dict[str, dict[str, PoseMatch]] = {}
    for name, per_seq in files.items():
        methods[name], matches[name] = {}, {}
        for seq, path in per_seq.items():
            methods[name][seq] = read_poses(path, fmt)
            matches[name][seq] = matchers[seq](methods[name][seq])
    single = (
        len(named) == 1 and named[0][0] is None and not gt.is_dir() and not named[0][1].is_dir()
    )
    directories = [p for p in [gt, *sources.values()] if p.is_dir()]
    return Inputs(gt_files, methods, matches, sources, single, directories)


def check_out(out: Path, inputs: Inputs, flag: str = "--out") -> None:
    """Refuse an output path inside an input directory, or a directory that is a file."""
    resolved = out.resolve()
    for directory in inputs.directories:
        d = directory.resolve()
        if resolved == d or d in resolved.parents:
            raise InputError(f"{flag} {out}: inside the input directory {directory}; "
                             "results are never written among the data")  # fmt: skip
    if flag == "--out" and out.exists() and not out.is_dir():
        raise InputError(f"{flag} {out}: exists and is not a directory")
