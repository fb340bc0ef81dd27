"""Writing output files and directories so that a reader never sees half of one, whatever
interrupts hifar: everything goes to a temporary sibling, is fsynced, and is renamed into place
(then the parent directory is fsynced, so the rename itself survives a crash)."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path
from typing import Callable, Mapping


def write_atomic(path: str | os.PathLike, content: bytes | str | Callable[[Path], None]) -> None:
  """Writes the file `path` through a temporary sibling.

  `content` is the bytes or text to write, or a function that writes the temporary path itself
  (matplotlib, PyAV); the temporary name keeps the file's extension for such writers. On any
  failure the temporary file is removed and `path` is left as it was.
  """
  path = Path(path)
  tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")
  try:
    if callable(content):
      content(tmp)
      with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    else:
      _write_synced(tmp, content.encode("utf-8") if isinstance(content, str) else content)
    os.replace(tmp, path)
  except BaseException:
    tmp.unlink(missing_ok=True)
    raise
  _fsync_dir(path.parent)


def write_dir_atomic(final: str | os.PathLike, files: Mapping[str, bytes]) -> None:
  """Writes the directory `final` holding `files` (name -> bytes) through a temporary sibling.

  An existing `final` (a checkpoint at the same env steps, e.g. re-reached after a resume) is
  replaced: it is moved aside first, so a crash leaves either the old or the new directory.
  """
  final = Path(final)
  parent = final.parent
  parent.mkdir(parents=True, exist_ok=True)
  tag = uuid.uuid4().hex[:8]
  tmp = parent / f".{final.name}.tmp-{os.getpid()}-{tag}"
  tmp.mkdir()
  try:
    for name, data in files.items():
      _write_synced(tmp / name, data)
    _fsync_dir(tmp)
    old = None
    if final.exists():
      old = parent / f".{final.name}.old-{os.getpid()}-{tag}"
      os.rename(final, old)
    os.rename(tmp, final)
    _fsync_dir(parent)
    if old is not None:
      shutil.rmtree(old, ignore_errors=True)
  except BaseException:
    shutil.rmtree(tmp, ignore_errors=True)
    raise


def _write_synced(path: Path, data: bytes) -> None:
  with open(path, "wb") as f:
    f.write(data)
    f.flush()
    os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
  fd = os.open(path, os.O_RDONLY)
  try:
    os.fsync(fd)
  finally:
    os.close(fd)
