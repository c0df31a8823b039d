"""A study's shard journal: finished shards appended to one file per run, synced in groups, replayed on resume.

One file per shard cost a temporary, an fsync, a rename and a directory listing each (a tenth of a small
study's time); a journal costs one append a shard and one fsync per `SYNC_SHARDS` shards or `SYNC_SECONDS`,
whichever comes first, and once more at the end of the run, before the table is written.

A record is a header (magic, lengths, SHA-256 of the rest) then the shard's key (JSON, with its arrays' names
and shapes) then the arrays as little-endian float64. Only the process that runs the study appends to its
journal (the executors' workers return their arrays to it), so a record is whole or is the file's torn tail:
a reader keeps the records before the first one that is short or whose digest does not match, and the
shards after it are computed again. A killed run (SIGKILL included) loses at most the records not yet
written; the operating system keeps what was written even if it was not synced, and a power cut loses at
most the unsynced group. Every run opens a journal of its own (never appending to another run's file), so
two journals may hold the same shard: a reader keeps the first (the values are the same: a shard depends
only on its key).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

MAGIC = b"WDJ1"
HEADER = struct.Struct("<4sIQ32s")  # magic, key length, arrays' length, SHA-256 of key + arrays
SYNC_SHARDS = 256  # records between syncs...
SYNC_SECONDS = 1.0  # ...or seconds since the last sync, whichever comes first
PATTERN = "journal-*.wdj"


def encode(key: str, arrays: dict[str, np.ndarray]) -> bytes:
    """One record: the header, the key with the arrays' names and shapes, the arrays (sorted by name)."""
    names = sorted(arrays)
    data = [np.ascontiguousarray(arrays[n], dtype="<f8") for n in names]
    meta = json.dumps({"key": key, "arrays": [[n, list(a.shape)] for n, a in zip(names, data, strict=True)]},
                      separators=(",", ":")).encode()
    body = b"".join(a.tobytes() for a in data)
    return HEADER.pack(MAGIC, len(meta), len(body), hashlib.sha256(meta + body).digest()) + meta + body


def decode(buf: bytes | memoryview) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
    """The whole records of a journal's bytes, in order, up to the first torn or damaged one."""
    at, end = 0, len(buf)
    while at + HEADER.size <= end:
        magic, n_meta, n_body, digest = HEADER.unpack_from(buf, at)
        start, stop = at + HEADER.size, at + HEADER.size + n_meta + n_body
        if magic != MAGIC or stop > end or hashlib.sha256(buf[start:stop]).digest() != digest:
            return
        try:
            meta = json.loads(bytes(buf[start:start + n_meta]))
            arrays, offset = {}, start + n_meta
            for name, shape in meta["arrays"]:
                count = int(np.prod(shape))
                arrays[name] = np.frombuffer(buf, dtype="<f8", count=count, offset=offset).reshape(shape).copy()
                offset += 8 * count
            key = meta["key"]
        except (ValueError, KeyError, TypeError):
            return
        if offset != stop or not isinstance(key, str):
            return
        yield key, arrays
        at = stop


def files(folder: str | os.PathLike) -> list[Path]:
    """A study folder's journals, oldest first (their names start with the time they were opened)."""
    return sorted((Path(folder) / "shards").glob(PATTERN))


def replay(folder: str | os.PathLike, wanted: set[str] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Every shard the folder's journals hold whole (the first record of a key), or only the `wanted` keys."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for path in files(folder):
        try:
            buf = path.read_bytes()
        except OSError:
            continue
        for key, arrays in decode(buf):
            if key not in out and (wanted is None or key in wanted):
                out[key] = arrays
    return out


class Writer:
    """Appends records to a new journal of this run; syncs every `sync_shards` records or `sync_seconds`."""

    def __init__(self, folder: str | os.PathLike, sync_shards: int = SYNC_SHARDS, sync_seconds: float = SYNC_SECONDS):
        shards = Path(folder) / "shards"
        shards.mkdir(parents=True, exist_ok=True)
        self.path = shards / f"journal-{time.time_ns():020d}-{os.getpid()}.wdj"
        self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o666)
        _sync_folder(shards)  # the new file's name survives a power cut too
        self.sync_shards, self.sync_seconds = sync_shards, sync_seconds
        self.pending = 0
        self.synced = time.monotonic()
        self.syncs = 0

    def append(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        data = memoryview(encode(key, arrays))
        while data:  # os.write may write less than asked (a signal, a full pipe); the rest follows
            data = data[os.write(self.fd, data):]
        self.pending += 1
        if self.pending >= self.sync_shards or time.monotonic() - self.synced >= self.sync_seconds:
            self.sync()

    def sync(self) -> None:
        if self.pending:
            os.fsync(self.fd)
            self.syncs += 1
        self.pending = 0
        self.synced = time.monotonic()

    def close(self) -> None:
        """Sync what is pending and close; a journal that holds nothing is removed."""
        if self.fd < 0:
            return
        try:
            self.sync()
        finally:
            empty = os.fstat(self.fd).st_size == 0
            os.close(self.fd)
            self.fd = -1
            if empty:
                with contextlib.suppress(OSError):
                    self.path.unlink()

    def __enter__(self) -> Writer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _sync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system can sync a folder
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
