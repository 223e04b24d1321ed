"""``motcomp export``: a recording in the forms other tools read.

* **MCAP for viewers** (Foxglove, PlotJuggler): every message as JSON (``message_encoding
  "json"``) on a channel with a JSON Schema (``schema encoding "jsonschema"``, the frames of
  docs/WIRE.md: :data:`SCHEMAS`), the recording's topics, times (``log_time``,
  ``publish_time``) and ``sequence`` unchanged, its ``motcomp`` metadata and ``config.json``
  attachment copied, and a ``motcomp_export`` metadata record naming the source.  A frame that
  does not fit its schema (a sender's bad frame: not msgpack, an unknown key, a NaN...) goes,
  as received, to the channel ``<key>/invalid`` (its bytes in base64, and why), so that every
  message of the export validates against its channel's schema and none is lost.
* **Tables for pandas**: one CSV or Parquet file per stream (``input``, ``output``,
  ``feedback``, ``status``), one row per message, columns ``log_time_ns``,
  ``publish_time_ns`` and the frame's fields (``pos.<axis>`` in every axis, NaN or empty where
  a frame lacks it; the output's ``flags`` joined by spaces; the status flattened into dotted
  paths, lists as JSON text).

The recording itself stays msgpack, as received: a replay computes with the very bytes the
service read (docs/REPLAY.md), which a re-encoded file cannot give, and the recorder spends no
time encoding while it records (docs/RECORDING.md).
"""

from __future__ import annotations

import base64
import csv
import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from motcomp import __version__
from motcomp.core.axes import AXES
from motcomp.errors import ConfigError, DataError, TransportError
from motcomp.record.mcapio import ScanResult, iter_records, metadata_dict
from motcomp.record.session import (
    DEFAULT_KEYS,
    FeedbackStream,
    InputStream,
    OutputStream,
    read_session,
    session_parts,
)

__all__ = ["FORMATS", "SCHEMAS", "ExportSummary", "export"]

FORMATS = ("mcap", "csv", "parquet")

_NUMBER = {"type": "number"}
_AXES_MAP = {"type": "object", "properties": {a: _NUMBER for a in AXES},
             "additionalProperties": False}

SCHEMAS: dict[str, dict[str, Any]] = {
    "input": {
        "title": "motcomp input frame (docs/WIRE.md)", "type": "object",
        "properties": {"seq": {"type": "integer"}, "t": _NUMBER,
                       "pos": {**_AXES_MAP, "minProperties": 1}},
        "required": ["seq", "pos"], "additionalProperties": False},
    "output": {
        "title": "motcomp output frame (docs/WIRE.md)", "type": "object",
        "properties": {"seq": {"type": "integer"}, "t": _NUMBER, "src_seq": {"type": "integer"},
                       "pos": {**_AXES_MAP, "required": list(AXES)},
                       "flags": {"type": "array", "items": {"type": "string"}},
                       "rx": {"type": "integer", "minimum": 0}},
        "required": ["seq", "t", "src_seq", "pos", "flags"], "additionalProperties": False},
    "feedback": {
        "title": "platform feedback frame (docs/WIRE.md)", "type": "object",
        "properties": {"t": _NUMBER,
                       "pos": {"type": "object", "additionalProperties": _NUMBER},
                       "acc": {"type": "object", "additionalProperties": _NUMBER}},
        "required": ["t", "pos"], "additionalProperties": False},
    "status": {
        "title": "motcomp service status (docs/DEPLOYMENT.md; NaN and infinities as null)",
        "type": "object",
        "properties": {"t": _NUMBER, "mode": {"type": "string"}, "ticks": {"type": "integer"},
                       "missed_ticks": {"type": "integer"}}},
    "other": {"title": "a recorded frame decoded from msgpack (a value that is not a map: "
                       "under 'value'; NaN and infinities as null)", "type": "object"},
    "invalid": {
        "title": "a recorded frame that does not fit its key's schema, as received",
        "type": "object",
        "properties": {"data_base64": {"type": "string", "contentEncoding": "base64"},
                       "reason": {"type": "string"}},
        "required": ["data_base64", "reason"], "additionalProperties": False},
}
"""The JSON Schema of each channel of an export for viewers, by role (``other``: a key of no
role, recorded through a wildcard)."""

INVALID_SUFFIX = "/invalid"


class _UnfitError(ValueError):
    """A frame that does not fit its schema (the message says why)."""


def _number(x: Any, where: str) -> float | int:
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise _UnfitError(f"{where} is not a number")
    if isinstance(x, float) and not math.isfinite(x):
        raise _UnfitError(f"{where} is {x!r}")
    return x


def _numbers(obj: Any, where: str, axes_only: bool) -> dict[str, float | int]:
    if not isinstance(obj, dict):
        raise _UnfitError(f"{where} is not a map")
    out = {}
    for k, v in obj.items():
        if not isinstance(k, str) or (axes_only and k not in AXES):
            raise _UnfitError(f"{where}: unknown axis {k!r}")
        out[k] = _number(v, f"{where}.{k}")
    return out


def _input(obj: Any) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise _UnfitError("not a map")
    unknown = set(obj) - {"seq", "t", "pos"}
    if unknown:
        raise _UnfitError(f"unknown key {sorted(map(str, unknown))[0]!r}")
    seq = obj.get("seq")
    if isinstance(seq, bool) or not isinstance(seq, int):
        raise _UnfitError("seq is missing or not an integer")
    out: dict[str, Any] = {"seq": seq}
    if "t" in obj:
        out["t"] = _number(obj["t"], "t")
    out["pos"] = _numbers(obj.get("pos"), "pos", axes_only=True)
    if not out["pos"]:
        raise _UnfitError("pos is empty")
    return out


_OUTPUT_KEYS = frozenset(SCHEMAS["output"]["properties"])


def _output(obj: Any) -> dict[str, Any]:
    if not isinstance(obj, dict) or not (
            {"seq", "t", "src_seq", "pos", "flags"} <= set(obj) <= _OUTPUT_KEYS):
        raise _UnfitError("not a map of seq, t, src_seq, pos, flags (and rx)")
    for k in ("seq", "src_seq", "rx"):
        if k in obj and (isinstance(obj[k], bool) or not isinstance(obj[k], int)):
            raise _UnfitError(f"{k} is not an integer")
    if obj.get("rx", 0) < 0:
        raise _UnfitError("rx is negative")
    pos = _numbers(obj["pos"], "pos", axes_only=True)
    if set(pos) != set(AXES):
        raise _UnfitError("pos does not carry the 8 axes")
    flags = obj["flags"]
    if not isinstance(flags, list) or not all(isinstance(f, str) for f in flags):
        raise _UnfitError("flags is not a list of strings")
    out = {"seq": obj["seq"], "t": _number(obj["t"], "t"), "src_seq": obj["src_seq"],
           "pos": pos, "flags": flags}
    if "rx" in obj:
        out["rx"] = obj["rx"]
    return out


def _feedback(obj: Any) -> dict[str, Any]:
    if not isinstance(obj, dict) or not {"t", "pos"} <= set(obj) <= {"t", "pos", "acc"}:
        raise _UnfitError("not a map of t, pos (and acc)")
    out: dict[str, Any] = {"t": _number(obj["t"], "t"),
                           "pos": _numbers(obj["pos"], "pos", axes_only=False)}
    if "acc" in obj:
        out["acc"] = _numbers(obj["acc"], "acc", axes_only=False)
    return out


def _free(obj: Any) -> dict[str, Any]:
    from motcomp.jsonsafe import finite

    out = finite(obj if isinstance(obj, dict) else {"value": obj})
    json.dumps(out, allow_nan=False)  # bytes and the like: TypeError
    return out


_CONVERT: dict[str, Callable[[Any], dict[str, Any]]] = {
    "input": _input, "output": _output, "feedback": _feedback, "status": _free, "other": _free}


def fit(role: str, payload: bytes) -> tuple[dict[str, Any] | None, str]:
    """``(json object, "")`` of a recorded frame that fits the schema of ``role``, else
    ``(None, why)``."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        return None, f"not msgpack: {str(exc)[:80]}"
    try:
        return _CONVERT[role](obj), ""
    except (_UnfitError, TypeError, ValueError) as exc:
        return None, str(exc)[:200]


@dataclass
class ExportSummary:
    paths: list[Path]
    format: str
    counts: dict[str, int] = field(default_factory=dict)
    """Messages (MCAP) or rows (tables) per channel or table."""
    invalid: dict[str, int] = field(default_factory=dict)
    """Frames that did not fit their key's schema, per key (MCAP)."""
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)

    def text(self) -> str:
        what = "messages" if self.format == "mcap" else "rows"
        lines = [f"exported {sum(self.counts.values())} {what} in {self.seconds:.1f} s to "
                 + ", ".join(map(str, self.paths))]
        lines += [f"  {k}: {n}" for k, n in sorted(self.counts.items())]
        lines += [f"  {k}: {n} frames that do not fit the schema, on {k}{INVALID_SUFFIX}"
                  for k, n in sorted(self.invalid.items()) if n]
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def export(source: str | Path, out: str | Path, fmt: str = "mcap",
           progress: Callable[[float], None] | None = None) -> ExportSummary:
    """Write ``source`` (a recording, or the name of a rotated one) as ``fmt`` to ``out``: an
    MCAP file, or a directory of tables (created if its parent exists).

    Raises
    ------
    DataError
        If the recording cannot be read.
    ConfigError
        If ``fmt`` is unknown, ``out``'s directory does not exist, or Parquet is asked without
        pyarrow.
    TransportError
        If ``out`` cannot be written.
    """
    if fmt not in FORMATS:
        raise ConfigError(f"export format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    out = Path(out)
    if not out.parent.is_dir():
        raise ConfigError(f"{out}: directory {out.parent} does not exist (create it first)")
    t0 = time.perf_counter()
    if fmt == "mcap":
        summary = _export_mcap(Path(source), out, progress)
    else:
        summary = _export_tables(Path(source), out, fmt)
    summary.seconds = time.perf_counter() - t0
    return summary


def _roles(parts: list[Path]) -> dict[str, str]:
    """Topic -> role, from the keys of the config recorded with the first part (else the
    defaults)."""
    from motcomp.record.mcapio import scan
    from motcomp.record.session import _config_attachment, _keys_of

    keys = dict(DEFAULT_KEYS)
    res = ScanResult(parts[0])
    for _ in scan(parts[0], set(), result=res, publish=False):
        pass
    cfg = _config_attachment(res, [])
    if cfg is not None:
        keys.update(_keys_of(cfg))
    return {v: k for k, v in keys.items()}


def _export_mcap(source: Path, out: Path, progress: Callable[[float], None] | None
                 ) -> ExportSummary:
    from mcap.writer import CompressionType, Writer

    from motcomp.record.mcapio import message_counts
    from motcomp.record.recorder import default_compression

    parts = session_parts(source)
    roles = _roles(parts)
    counts = [message_counts(p) for p in parts]
    total = sum(sum(n for k, n in c.items() if k) for c in counts if c) or 0
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE}[default_compression()]
    summary = ExportSummary([out], "mcap")
    try:
        fh = out.open("wb")
    except OSError as exc:
        raise TransportError(f"{out}: cannot write: {exc.strerror}") from None
    with fh:
        w = Writer(fh, compression=comp)
        w.start(profile="", library=f"motcomp {__version__} export")
        schema_ids: dict[str, int] = {}
        channels: dict[str, int] = {}

        def channel(topic: str, role: str) -> int:
            cid = channels.get(topic)
            if cid is None:
                if role not in schema_ids:
                    schema_ids[role] = w.register_schema(
                        name=f"motcomp.{role}", encoding="jsonschema",
                        data=json.dumps(SCHEMAS[role]).encode())
                cid = channels[topic] = w.register_channel(
                    topic=topic, message_encoding="json", schema_id=schema_ids[role],
                    metadata={"zenoh_key": topic.removesuffix(INVALID_SUFFIX)})
            return cid

        done = 0
        results = []
        for part in parts:
            res = ScanResult(part)
            results.append(res)
            for rec in iter_records(part, result=res):
                role = roles.get(rec.topic, "other")
                obj, why = fit(role, rec.data)
                if obj is None:
                    topic = rec.topic + INVALID_SUFFIX
                    obj = {"data_base64": base64.b64encode(rec.data).decode("ascii"),
                           "reason": why}
                    cid = channel(topic, "invalid")
                    summary.invalid[rec.topic] = summary.invalid.get(rec.topic, 0) + 1
                else:
                    topic = rec.topic
                    cid = channel(topic, role)
                w.add_message(cid, log_time=rec.log_ns, publish_time=rec.publish_ns,
                              sequence=rec.sequence,
                              data=json.dumps(obj, separators=(",", ":"),
                                              allow_nan=False).encode())
                summary.counts[topic] = summary.counts.get(topic, 0) + 1
                done += 1
                if progress is not None and total and done % 20000 == 0:
                    progress(done / total)
        cut = [r for r in results if r.truncated and not r.complete]
        if cut and not done:  # as every reader: nothing recovered is nothing to export
            fh.close()
            out.unlink(missing_ok=True)
            raise DataError(f"{cut[0].path}: unfinished recording ({cut[0].truncated}) with no "
                            "complete chunk: no message to export")
        summary.warnings += [f"{r.path}: unfinished recording ({r.truncated}): exported its "
                             f"{r.messages} messages up to its last complete chunk" for r in cut]
        _copy_metadata(w, results, source)
        w.finish()
    return summary


def _copy_metadata(w: Any, results: list[ScanResult], source: Path) -> None:
    """The source's ``motcomp`` metadata (its last record, as readers take it: the recorder
    writes it again when it learns the service's config), its attachments (the last of each
    name) and an export record."""
    last = ScanResult(source)
    last.metadata = [m for res in results for m in res.metadata]
    meta = metadata_dict(last)
    if meta:
        w.add_metadata("motcomp", {k: json.dumps(v) if k == "keys" else str(v)
                                   for k, v in meta.items()})
    attachments = {name: (media, data) for res in results
                   for name, media, data in res.attachments}
    for name, (media, data) in attachments.items():
        w.add_attachment(0, 0, name, media, data)
    w.add_metadata("motcomp_export", {"source": str(source), "version": __version__,
                                      "encoding": "json with JSON Schema (docs/RECORDING.md)"})


# --- tables -------------------------------------------------------------------------------------
def _tables(source: Path) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
    """``(name, columns)`` of each stream of the recording (columns of equal length)."""
    from motcomp.record.frames import FLAG_BITS

    s = read_session(source, other_keys=False)
    names = sorted(FLAG_BITS, key=lambda k: FLAG_BITS[k])
    for name, st in (("input", s.inputs), ("output", s.outputs), ("feedback", s.feedback)):
        if st is None:
            continue
        cols: dict[str, np.ndarray] = {"log_time_ns": st.log_ns,
                                       "publish_time_ns": st.publish_ns}
        if isinstance(st, InputStream):
            # empty where the frame was not decoded (no seq to give): never a seq 0 of its own
            cols.update(seq=np.array([int(q) if d else None for q, d in
                                      zip(st.seq.tolist(), st.decoded.tolist(), strict=True)],
                                     dtype=object), t=st.t, decoded=st.decoded)
        elif isinstance(st, OutputStream):
            cols.update(seq=st.seq, t=st.t, src_seq=st.src_seq, rx=st.rx, valid=st.valid)
        elif isinstance(st, FeedbackStream):
            cols.update(t=st.t, valid=st.valid)
        for a, axis in enumerate(AXES):
            cols[f"pos.{axis}"] = st.pos[:, a]
        if isinstance(st, FeedbackStream):
            for a, axis in enumerate(AXES):
                cols[f"acc.{axis}"] = st.acc[:, a]
        if isinstance(st, OutputStream):
            cols["flags"] = np.array([" ".join(f for f in names if bits & FLAG_BITS[f])
                                      for bits in st.flags.tolist()], dtype=object)
        yield name, cols
    if s.status:
        rows = [(ns, _flatten(st)) for ns, st in s.status]
        keys = sorted({k for _, row in rows for k in row})
        cols = {"log_time_ns": np.array([ns for ns, _ in rows], dtype=np.int64)}
        for k in keys:
            cols[k] = np.array([row.get(k) for _, row in rows], dtype=object)
        yield "status", cols


def _flatten(obj: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Scalar leaves of a status map as ``{"a.b": value}``; lists as JSON text."""
    from motcomp.jsonsafe import finite

    out: dict[str, Any] = {}
    for k, v in obj.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        elif isinstance(v, list | tuple):
            out[key] = json.dumps(finite(v), default=str)
        else:
            out[key] = finite(v)
    return out


def _export_tables(source: Path, out: Path, fmt: str) -> ExportSummary:
    if fmt == "parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise ConfigError("Parquet needs pyarrow: pip install 'motcomp[parquet]' (or "
                              "--format csv)") from None
    try:
        out.mkdir(exist_ok=True)
    except OSError as exc:
        raise TransportError(f"{out}: cannot create the directory: {exc.strerror}") from None
    summary = ExportSummary([], fmt)
    for name, cols in _tables(source):
        path = out / f"{name}.{fmt}"
        n = len(next(iter(cols.values())))
        try:
            if fmt == "csv":
                _write_csv(path, cols)
            else:
                table = pa.table({k: (_arrow(pa, v) if v.dtype == object else v)
                                  for k, v in cols.items()})
                pq.write_table(table, path)
        except OSError as exc:
            raise TransportError(f"{path}: cannot write: {exc.strerror}") from None
        summary.paths.append(path)
        summary.counts[name] = n
    if not summary.paths:
        raise DataError(f"{source}: no input, output, feedback or status messages to export")
    return summary


def _arrow(pa: Any, values: np.ndarray) -> Any:
    """An Arrow column of Python values; as text if they mix types Arrow cannot unify."""
    try:
        return pa.array(values.tolist())
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return pa.array([None if v is None else str(v) for v in values.tolist()])


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else repr(v)
    if isinstance(v, bool):
        return "1" if v else "0"
    return str(v)


def _write_csv(path: Path, cols: dict[str, np.ndarray]) -> None:
    """One row per message; floats as the shortest text that reads back to the same double,
    NaN and None as an empty cell (pandas reads it as NaN), booleans as 1/0."""
    lists = [c.tolist() for c in cols.values()]
    with path.open("w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(list(cols))
        for row in zip(*lists, strict=True):
            wr.writerow([_cell(v) for v in row])
