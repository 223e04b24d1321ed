"""MCAP files of motcomp sessions: writing (through the ``mcap`` package) and fast reading.

Writing uses :class:`mcap.writer.Writer` unchanged (see docs/RECORDING.md for the layout).

Reading is done here rather than with ``mcap.reader``: the stock readers build one Python object
per record (message *and* message-index entry), a few microseconds each, which is most of the
time budget of an offline replay of an hour at 1 kHz (about 11 million messages).  This reader
walks only the top-level records in Python (a few per megabyte), decompresses each chunk in one
call, and takes the position of every message from the chunk's *message index* records, which
it decodes with numpy; the message header fields (channel, sequence, log and publish time) are
then gathered for all messages of a batch at once.  A chunk whose message index is missing or
incomplete (the last chunk of an unfinished file, or a file written without indexes) is walked
record by record instead.

Truncated files
    An unfinished file (recorder killed, power cut) has no summary or footer and may end inside
    a record.  Reading stops at the last complete top-level record; every complete chunk before
    it is used.  :attr:`ScanResult.truncated` tells, with the byte offset, and the caller reports
    how many messages were recovered.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import numpy as np

from motcomp.errors import DataError

__all__ = [
    "MAGIC",
    "ChannelInfo",
    "MessageBatch",
    "Record",
    "ScanResult",
    "iter_messages",
    "iter_record_batches",
    "iter_records",
    "message_counts",
    "scan",
    "topic_span",
]

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_ATTACHMENT, OP_METADATA, OP_DATA_END = 0x07, 0x09, 0x0C, 0x0F
_MSG_HEADER = 22  # channel u16, sequence u32, log_time u64, publish_time u64
PAD = 1024
"""Zero bytes appended to every batch buffer, so fixed-width row views never run off its end."""


@dataclass(frozen=True)
class ChannelInfo:
    id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass
class MessageBatch:
    """The messages of one channel found in a batch of chunks, in file order.

    ``buf`` is the batch's uncompressed bytes (zero-padded by :data:`PAD`); message ``i``'s
    payload is ``buf[offset[i] : offset[i] + length[i]]``.
    """

    channel: ChannelInfo
    buf: np.ndarray
    offset: np.ndarray
    length: np.ndarray
    log_ns: np.ndarray
    publish_ns: np.ndarray
    """Empty unless the scan was asked for it."""

    def __len__(self) -> int:
        return int(self.offset.size)

    def payload(self, i: int) -> bytes:
        o = int(self.offset[i])
        return bytes(self.buf[o:o + int(self.length[i])])

    def sequences(self) -> np.ndarray:
        """The messages' MCAP ``sequence`` fields (u32)."""
        at = self.offset - _MSG_HEADER + 2  # after the channel id
        b = self.buf
        return (b[at].astype(np.int64) | b[at + 1].astype(np.int64) << 8
                | b[at + 2].astype(np.int64) << 16 | b[at + 3].astype(np.int64) << 24)


@dataclass
class ScanResult:
    """What a scan found besides the messages."""

    path: Path
    profile: str = ""
    library: str = ""
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    attachments: list[tuple[str, str, bytes]] = field(default_factory=list)
    messages: int = 0
    chunks: int = 0
    walked_chunks: int = 0
    complete: bool = False
    truncated: str = ""
    """Empty for a complete file, else what was cut and where."""
    damaged: bool = False
    """The read stopped at a chunk that is corrupt (not where the file ends)."""


def _u16(b: bytes | memoryview, o: int) -> int:
    return int(struct.unpack_from("<H", b, o)[0])


def _u32(b: bytes | memoryview, o: int) -> int:
    return int(struct.unpack_from("<I", b, o)[0])


def _u64(b: bytes | memoryview, o: int) -> int:
    return int(struct.unpack_from("<Q", b, o)[0])


def _string(b: bytes | memoryview, o: int) -> tuple[str, int]:
    n = _u32(b, o)
    return bytes(b[o + 4:o + 4 + n]).decode("utf-8", "replace"), o + 4 + n


def _string_map(b: bytes | memoryview, o: int) -> tuple[dict[str, str], int]:
    n = _u32(b, o)
    end = o + 4 + n
    o += 4
    out: dict[str, str] = {}
    while o < end:
        k, o = _string(b, o)
        v, o = _string(b, o)
        out[k] = v
    return out, end


def _channel(body: bytes | memoryview) -> ChannelInfo:
    cid = _u16(body, 0)
    topic, o = _string(body, 4)
    enc, o = _string(body, o)
    meta, _ = _string_map(body, o)
    return ChannelInfo(cid, topic, enc, meta)


def _decompress_into(compression: str, data: memoryview, out: memoryview) -> int:
    """Decompress ``data`` into ``out`` (exactly its size); returns the bytes written."""
    if compression == "":
        n = min(len(data), len(out))
        out[:n] = data[:n]
        return n
    if compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(data)
        n = 0
        while n < len(out):
            got = reader.readinto(out[n:])
            if not got:
                break
            n += got
        return n
    if compression == "lz4":
        import lz4.frame

        raw = lz4.frame.decompress(bytes(data))
        n = min(len(raw), len(out))
        out[:n] = raw[:n]
        return len(raw)
    raise DataError(f"unsupported MCAP chunk compression {compression!r}")


@dataclass
class _Chunk:
    data: memoryview
    index: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Channel -> (record offsets, log times) from the message index records."""
    indexed: bool = False


class _Batcher:
    """Accumulates chunks and turns them into per-channel :class:`MessageBatch` es."""

    def __init__(self, res: ScanResult, topics: set[str] | None, batch_bytes: int,
                 publish: bool) -> None:
        self.res = res
        self.publish = publish
        self.topics = topics
        self.batch_bytes = batch_bytes
        self.buf = np.empty(batch_bytes + PAD, dtype=np.uint8)
        self.offsets: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        self.size = 0

    def space(self, size: int) -> memoryview:
        """Where the next chunk's ``size`` bytes go (the caller flushes a full batch first)."""
        if self.size + size + PAD > self.buf.size:
            grown = np.empty(max(self.size + size + PAD, 2 * self.buf.size), dtype=np.uint8)
            grown[:self.size] = self.buf[:self.size]
            self.buf = grown
        return memoryview(self.buf)[self.size:self.size + size]  # type: ignore[arg-type]

    def fits(self, size: int) -> bool:
        return self.size == 0 or self.size + size + PAD <= self.buf.size

    def wanted(self, cid: int) -> bool:
        ch = self.res.channels.get(cid)
        return ch is not None and (self.topics is None or ch.topic in self.topics)

    def add(self, chunk: _Chunk) -> None:
        res = self.res
        res.chunks += 1
        data = chunk.data
        unknown = [c for c in chunk.index if c not in res.channels]
        if not chunk.indexed or unknown:
            walked = self._walk(data, need=None if not chunk.indexed else set(unknown))
            if not chunk.indexed:
                res.walked_chunks += 1
                chunk.index = walked
        base = self.size
        for cid, (offs, logs) in chunk.index.items():
            res.messages += int(offs.size)
            if self.wanted(cid) and offs.size:
                self.offsets.setdefault(cid, []).append((offs + base, logs))
        self.size += len(data)

    def _walk(self, data: memoryview, need: set[int] | None
              ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Record-by-record walk of a chunk's records: registers its channels, and returns the
        message offsets per channel (stops early once the channels in ``need`` are known)."""
        res = self.res
        offs: dict[int, list[int]] = {}
        logs: dict[int, list[int]] = {}
        o, n = 0, len(data)
        while o + 9 <= n:
            op = data[o]
            length = _u64(data, o + 1)
            end = o + 9 + length
            if end > n:
                break
            if op == OP_CHANNEL:
                ch = _channel(data[o + 9:end])
                res.channels[ch.id] = ch
                if need is not None:
                    need.discard(ch.id)
                    if not need:
                        return {}
            elif op == OP_MESSAGE and need is None and length >= _MSG_HEADER:
                cid = _u16(data, o + 9)
                offs.setdefault(cid, []).append(o)
                logs.setdefault(cid, []).append(_u64(data, o + 15))
            o = end
        return {c: (np.asarray(v, dtype=np.int64), np.asarray(logs[c], dtype=np.int64))
                for c, v in offs.items()}

    def flush(self) -> list[MessageBatch]:
        if not self.size:
            return []
        buf = self.buf[:self.size + PAD]
        buf[self.size:] = 0
        n = buf.size - 8
        u64 = np.ndarray((n,), dtype="<u8", buffer=buf, offset=0, strides=(1,))
        out = []
        for cid, parts in self.offsets.items():
            o = np.concatenate([p[0] for p in parts]) if len(parts) > 1 else parts[0][0]
            logs = np.concatenate([p[1] for p in parts]) if len(parts) > 1 else parts[0][1]
            ok = buf[o] == OP_MESSAGE
            if not ok.all():
                o, logs = o[ok], logs[ok]
            length = u64[o + 1].astype(np.int64) - _MSG_HEADER
            out.append(MessageBatch(
                channel=self.res.channels[cid], buf=buf, offset=o + 9 + _MSG_HEADER,
                length=length, log_ns=logs.astype(np.int64),
                publish_ns=(u64[o + 23].astype(np.int64) if self.publish
                            else np.zeros(0, np.int64))))
        self.buf = np.empty(self.batch_bytes + PAD, dtype=np.uint8)
        self.offsets, self.size = {}, 0
        return out


def _read_record(f: BinaryIO) -> tuple[int, bytes] | None:
    head = f.read(9)
    if len(head) < 9:
        return None if not head else (-1, b"")
    op, length = head[0], _u64(head, 1)
    body = f.read(length)
    if len(body) < length:
        return -1, b""
    return op, body


def scan(path: str | Path, topics: set[str] | None = None, batch_bytes: int = 48 << 20,
         result: ScanResult | None = None, publish: bool = True,
         check_crc: bool = False) -> Iterator[list[MessageBatch]]:
    """Yield lists of :class:`MessageBatch` (one per wanted channel) for batches of about
    ``batch_bytes`` of uncompressed chunk data.  ``result`` (filled in as the scan goes) receives
    the channels, metadata, attachments, counts and the truncation diagnosis.  ``publish``:
    gather the messages' publish times; ``check_crc``: verify each chunk's CRC (about 1 ns a
    byte; the size is always checked).

    Raises
    ------
    DataError
        If the file cannot be opened or is not an MCAP file.
    """
    p = Path(path)
    res = result if result is not None else ScanResult(p)
    res.path = p
    batcher = _Batcher(res, topics, batch_bytes, publish)
    loose = bytearray()  # top-level (unchunked) message records, as one pseudo chunk
    try:
        f = p.open("rb")
    except OSError as exc:
        raise DataError(f"{p}: cannot open: {exc.strerror}") from None
    with f:
        if f.read(8) != MAGIC:
            raise DataError(f"{p}: not an MCAP file (bad magic)")
        pending: _Chunk | None = None
        while True:
            pos = f.tell()
            rec = _read_record(f)
            if rec is None or rec[0] == -1:
                size = os.fstat(f.fileno()).st_size
                res.truncated = (f"the file ({size} bytes) ends inside the record that starts "
                                 f"at byte {pos}" if rec is not None
                                 else f"the file ({size} bytes) ends at byte {pos} without a "
                                      "footer")
                break
            op, body = rec
            if op == OP_MESSAGE_INDEX and pending is not None:
                cid = _u16(body, 0)
                m = _u32(body, 2) // 16
                pairs = np.frombuffer(body, dtype="<u8", count=2 * m, offset=6).reshape(m, 2)
                pending.index[cid] = (pairs[:, 1].astype(np.int64), pairs[:, 0].astype(np.int64))
                continue
            if pending is not None:  # a complete record follows its index: trust the index
                pending.indexed = bool(pending.index)
                batcher.add(pending)
                pending = None
            if op == OP_CHUNK:
                o = 8 + 8
                size = _u64(body, o)
                crc = _u32(body, o + 8)
                comp, o = _string(body, o + 12)
                n = _u64(body, o)
                if not batcher.fits(size):
                    yield batcher.flush()
                data = batcher.space(size)
                try:
                    got = _decompress_into(comp, memoryview(body)[o + 8:o + 8 + n], data)
                except DataError:
                    raise
                except Exception as exc:  # a corrupt chunk: report, keep what came before
                    res.truncated = f"chunk at byte {pos} cannot be decompressed ({exc})"
                    res.damaged = True
                    break
                if got != size or (check_crc and crc and zlib.crc32(data) != crc):
                    res.truncated = f"chunk at byte {pos} is corrupt (size or CRC mismatch)"
                    res.damaged = True
                    break
                pending = _Chunk(data)
            elif op == OP_CHANNEL:
                ch = _channel(body)
                res.channels[ch.id] = ch
            elif op == OP_MESSAGE:
                loose += bytes([OP_MESSAGE]) + struct.pack("<Q", len(body)) + body
            elif op == OP_HEADER:
                res.profile, o = _string(body, 0)
                res.library, _ = _string(body, o)
            elif op == OP_METADATA:
                name, o = _string(body, 0)
                meta, _ = _string_map(body, o)
                res.metadata.append((name, meta))
            elif op == OP_ATTACHMENT:
                name, o = _string(body, 16)
                media, o = _string(body, o)
                n = _u64(body, o)
                res.attachments.append((name, media, bytes(body[o + 8:o + 8 + n])))
            elif op in (OP_DATA_END, OP_FOOTER):
                res.complete = True
                break
        if pending is not None:  # the last chunk, its index possibly incomplete: walk it
            batcher.add(_Chunk(pending.data))
        if loose:
            if not batcher.fits(len(loose)):
                yield batcher.flush()
            view = batcher.space(len(loose))
            view[:] = loose
            batcher.add(_Chunk(view))
    yield batcher.flush()


OP_CHUNK_INDEX, OP_STATISTICS = 0x08, 0x0B


def _summary(path: Path) -> bytes | None:
    """The summary section of a finished file (None without a usable footer)."""
    try:
        with path.open("rb") as f:
            f.seek(0, 2)
            size = f.tell()
            if size < 8 + 29 + 8:
                return None
            f.seek(size - 8 - 29)
            tail = f.read(29 + 8)
            if tail[-8:] != MAGIC or tail[0] != OP_FOOTER:
                return None
            start = _u64(tail, 9)
            if not 8 <= start < size:
                return None
            f.seek(start)
            return f.read(size - 8 - 29 - start)
    except OSError:
        return None


def _summary_records(summary: bytes) -> Iterator[tuple[int, memoryview]]:
    o = 0
    while o + 9 <= len(summary):
        op, length = summary[o], _u64(summary, o + 1)
        yield op, memoryview(summary)[o + 9:o + 9 + length]
        o += 9 + length


def message_counts(path: str | Path) -> dict[str, Any] | None:
    """Messages per topic from the summary section (None if the file has no usable summary,
    e.g. an unfinished recording); key ``""`` holds ``(first, last)`` log time."""
    summary = _summary(Path(path))
    if summary is None:
        return None
    topics: dict[int, str] = {}
    counts: dict[int, int] = {}
    t_first = t_last = 0
    for op, body in _summary_records(summary):
        if op == OP_CHANNEL:
            ch = _channel(body)
            topics[ch.id] = ch.topic
        elif op == OP_STATISTICS:
            t_first, t_last = _u64(body, 8 + 2 + 4 * 4), _u64(body, 8 + 2 + 4 * 4 + 8)
            q = 8 + 2 + 4 * 4 + 8 + 8
            n = _u32(body, q)
            q += 4
            for _ in range(n // 10):
                counts[_u16(body, q)] = _u64(body, q + 2)
                q += 10
    if not counts or not topics:
        return None
    out: dict[str, Any] = {"": (t_first, t_last)}
    for cid, n in counts.items():
        if cid in topics:
            out[topics[cid]] = out.get(topics[cid], 0) + n
    return out


def topic_span(path: str | Path, topic: str) -> tuple[int, int] | None:
    """``(first, last)`` log time of ``topic``'s messages, from the summary's chunk indexes and
    the message indexes of the first and last chunk holding it (two small reads, not a scan).
    None if the file has no usable summary or indexes, or no message on ``topic``."""
    p = Path(path)
    summary = _summary(p)
    if summary is None:
        return None
    ids: set[int] = set()
    offsets: list[tuple[int, int]] = []  # (chunk's first log time, its message index offset)
    for op, body in _summary_records(summary):
        if op == OP_CHANNEL:
            ch = _channel(body)
            if ch.topic == topic:
                ids.add(ch.id)
        elif op == OP_CHUNK_INDEX:
            start_ns = _u64(body, 0)
            n = _u32(body, 32)
            for q in range(36, 36 + n, 10):
                if _u16(body, q) in ids:
                    offsets.append((start_ns, _u64(body, q + 2)))
    if not offsets:
        return None
    offsets.sort()
    times: list[int] = []
    try:
        with p.open("rb") as f:
            for _, at in {offsets[0], offsets[-1]}:
                f.seek(at)
                head = f.read(9 + 2 + 4)
                if len(head) < 15 or head[0] != OP_MESSAGE_INDEX:
                    return None
                rows = f.read(_u32(head, 11))
                times += [_u64(rows, q) for q in range(0, len(rows) - 15, 16)]
    except OSError:
        return None
    return (min(times), max(times)) if times else None


class Record(NamedTuple):
    """One message of a file, as :func:`iter_records` yields it."""

    topic: str
    sequence: int
    log_ns: int
    publish_ns: int
    data: bytes


def iter_record_batches(path: str | Path, topics: set[str] | None = None,
                        result: ScanResult | None = None, batch_bytes: int = 4 << 20
                        ) -> Iterator[list[Record]]:
    """The messages (:class:`Record`) of each batch of about ``batch_bytes`` of chunks, in file
    order (memory stays bounded by the batch size; empty batches are skipped)."""
    for batch in scan(path, topics, batch_bytes=batch_bytes, result=result):
        rows = []
        for mb in batch:
            seq = mb.sequences()
            for i in range(len(mb)):
                rows.append((int(mb.offset[i]), Record(mb.channel.topic, int(seq[i]),
                                                       int(mb.log_ns[i]), int(mb.publish_ns[i]),
                                                       mb.payload(i))))
        if rows:
            rows.sort(key=lambda r: r[0])
            yield [rec for _, rec in rows]


def iter_records(path: str | Path, topics: set[str] | None = None,
                 result: ScanResult | None = None) -> Iterator[Record]:
    """Each message (:class:`Record`) in file order, batch by batch (memory stays bounded by
    the batch size)."""
    for batch in iter_record_batches(path, topics, result):
        yield from batch


def iter_messages(path: str | Path, topics: set[str] | None = None,
                  result: ScanResult | None = None) -> Iterator[tuple[str, int, int, bytes]]:
    """``(topic, log_ns, publish_ns, payload)`` of each message, in file order (as
    :func:`iter_records`)."""
    for rec in iter_records(path, topics, result):
        yield rec.topic, rec.log_ns, rec.publish_ns, rec.data


def metadata_dict(res: ScanResult, name: str = "motcomp") -> dict[str, Any]:
    """The metadata record ``name`` (the last one if several), JSON values decoded."""
    out: dict[str, Any] = {}
    for n, meta in res.metadata:
        if n == name:
            out = {}
            for k, v in meta.items():
                try:
                    out[k] = json.loads(v) if k == "keys" else v
                except ValueError:
                    out[k] = v
    return out
