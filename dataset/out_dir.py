"""An output directory written as one step: made beside its place, then renamed into it, so a
reader never sees half of it and a failure leaves what was there before as it was."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from dataset.records import DatasetError

T = TypeVar("T")


def check_apart(out: str | os.PathLike[str], sources: Sequence[str | os.PathLike[str]]) -> None:
    """DatasetError if ``out`` is one of ``sources``, inside one or holds one: replacing it would
    lose a source, and a dataset holds only its own files."""
    target = Path(out).resolve()
    for source in sources:
        root = Path(source).resolve()
        if target == root or root in target.parents or target in root.parents:
            raise DatasetError(f"--out {out} overlaps the dataset {source}: give a directory apart from it")


def write_directory(out: str | os.PathLike[str], force: bool, write: Callable[[Path], T]) -> T:
    """``write(staging)`` fills a new directory beside ``out``, which then takes ``out``'s place;
    returns what ``write`` returned. An existing ``out`` is refused (FileExistsError) unless
    ``force``, and then replaced only once the new one is complete. A failure anywhere, ``write``'s
    own included, leaves no new directory and ``out`` as it was."""
    target = Path(out)
    _refuse_existing(target, force)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.new.", dir=target.parent))
    try:
        staging.chmod(0o755)  # mkdtemp's directory is private; the output is not
        result = write(staging)
        _refuse_existing(target, force)  # made while this one was written
        _take_place(staging, target)
        return result
    finally:
        if staging.exists():
            shutil.rmtree(staging)


def _refuse_existing(target: Path, force: bool) -> None:
    if not (target.exists() or target.is_symlink()):
        return
    if not force:
        raise FileExistsError(f"{target} exists; give --force to replace it (it is replaced whole, never half-way)")
    if target.is_symlink() or not target.is_dir():
        raise FileExistsError(f"{target} exists and is not a directory; --force replaces only a directory")


def _take_place(staging: Path, target: Path) -> None:
    """Rename ``staging`` to ``target``; an existing ``target`` is moved aside first, put back if
    the rename fails, and deleted once the new directory is in its place."""
    if not target.exists():
        staging.rename(target)
        return
    aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
    target.rename(aside / target.name)
    try:
        staging.rename(target)
    except OSError:
        (aside / target.name).rename(target)
        aside.rmdir()
        raise
    shutil.rmtree(aside)
