"""Writing files so that a crash never leaves half of one: the one atomic JSON writer."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def write_json_atomic(path: Path, doc: Any, *, indent: int = 2, sort_keys: bool = False, mode: int = 0o644) -> None:
    """Write ``doc`` as JSON to ``path`` atomically: into a temporary file in the same folder
    (``.<name>.*.tmp``), flushed to disk, then renamed over ``path``. A reader sees the old file or
    the new one, never a part; a crash leaves at most the temporary file, which is removed when
    the write fails in this process. ``mode`` is the file's permission bits.

    Raises:
        OSError: the folder cannot be written (the caller words it).
        TypeError: ``doc`` holds something JSON cannot encode.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=indent, sort_keys=sort_keys)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_error(e: OSError | UnicodeDecodeError) -> str:
    """Why a file could not be read as text, in words for a one-line error: ``it is not text (byte
    0x89 at offset 0 is not UTF-8)`` for a binary file, else the system's reason (``Permission
    denied``, ``Is a directory``)."""
    if isinstance(e, UnicodeDecodeError):
        byte = e.object[e.start] if e.start < len(e.object) else None
        at = f"byte 0x{byte:02x} at offset {e.start}" if isinstance(byte, int) else f"offset {e.start}"
        return f"it is not text ({at} is not UTF-8)"
    return e.strerror or e.__class__.__name__
