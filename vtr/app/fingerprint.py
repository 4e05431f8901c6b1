"""What a run read, by content: the fingerprint a batch resume compares (README, "Batches": "Resume").

Every file of a source (a folder: all files below it, in path order; or one file, a bag) contributes its path relative
to the source, its size and modification time, and its content: the whole content of files up to
``SMALL_FILE_BYTES`` (calibration, times, poses, YAML), the first and last ``SAMPLE_BYTES`` of larger ones (images,
bags). So a recalibrated ``calib.txt`` of the same size, two images swapped, a file touched, added or removed all change
the fingerprint, while a large source is read in ~8 KiB per file, not whole.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

#: files up to this size are hashed whole (bytes)
SMALL_FILE_BYTES = 65_536
#: larger files: this many bytes from each end are hashed (with the size and modification time)
SAMPLE_BYTES = 4_096


def source_fingerprint(source: Path) -> str:
    """Hex BLAKE2b fingerprint of the files a run reads from ``source`` (see the module doc)."""
    src = Path(source)
    files = [src] if src.is_file() else sorted(f for f in src.rglob("*") if f.is_file())
    h = hashlib.blake2b(digest_size=20)
    for f in files:
        st = f.stat()
        rel = f.name if f == src else str(f.relative_to(src))
        h.update(f"{rel}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
        with open(f, "rb") as fh:
            if st.st_size <= SMALL_FILE_BYTES:
                h.update(fh.read())
            else:
                h.update(fh.read(SAMPLE_BYTES))
                fh.seek(-SAMPLE_BYTES, 2)
                h.update(fh.read(SAMPLE_BYTES))
    return h.hexdigest()


__all__ = ["SAMPLE_BYTES", "SMALL_FILE_BYTES", "source_fingerprint"]
