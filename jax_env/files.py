"""Writing output files so that a reader never sees half of one, whatever interrupts hifar."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Callable


def write_atomic(path: str | os.PathLike, content: bytes | str | Callable[[Path], None]) -> None:
  """Writes `path` through a temporary sibling: write, fsync, rename, fsync the directory.

  `content` is the bytes or text to write, or a function that writes the temporary path itself
  (matplotlib, PyAV); the temporary name keeps the file's extension for such writers. On any
  failure the temporary file is removed and `path` is left as it was.
  """
  path = Path(path)
  tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")
  try:
    if callable(content):
      content(tmp)
    else:
      data = content.encode("utf-8") if isinstance(content, str) else content
      tmp.write_bytes(data)
    with open(tmp, "rb") as f:
      os.fsync(f.fileno())
    os.replace(tmp, path)
  except BaseException:
    tmp.unlink(missing_ok=True)
    raise
  fd = os.open(path.parent, os.O_RDONLY)
  try:
    os.fsync(fd)
  finally:
    os.close(fd)
