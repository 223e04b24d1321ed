"""CAN output of corrected setpoints, and its receiving side for the simulated platform.

Layout (``config/motcomp.dbc``, the contract; classic CAN, 8-byte frames, Intel byte order):
four frames of two axes each, ids 0x100-0x103 -- rails x/y, hexapod x/y, z/roll, pitch/yaw.
Each frame: two signed 24-bit positions (1 um or 1 urad per bit, +-8.39 m/rad), ``FLAGS``
(4 bits: first/second axis limited, input stale, parking/start-up), ``ALIVE`` (4-bit rolling
counter per frame) and ``CRC`` (CRC-8 SAE J1850 over the id and bytes 0-6).

The DBC is loaded with cantools.  For the 1 kHz loop, frames are packed by a layout *compiled*
from the DBC at start-up (:class:`FrameLayout`): cantools' ``encode`` costs 13-30 us a frame here,
the compiled packer ~2 us, and the tests check that both give the same bytes.  The receiving
side (:class:`CanSetpointReceiver`) decodes with cantools and checks CRC and alive counter.

Bus load: a classic frame with an 11-bit id and 8 data bytes is 111 bits plus up to 24 stuff
bits, plus 3 bits of interframe space.  :func:`bus_load` gives the load of the 4-frame layout;
at 1 Mbit/s: 1000 Hz -> 46-55 %, 500 Hz -> 23-28 %, 250 Hz -> 11-14 %.  Keep a shared bus
below ~50 %: send every 2nd or 4th tick at 1 kHz (``output.can.send_every``).  The four
frames of a cycle go out on consecutive ticks (staggered), so one tick never carries them all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from motcomp.core.axes import AXES
from motcomp.core.tick import TickOutput
from motcomp.errors import ConfigError, FrameError, TransportError

if TYPE_CHECKING:
    from motcomp.config import CanConfig

__all__ = [
    "CanSetpointReceiver",
    "CanSink",
    "FrameLayout",
    "bus_load",
    "crc8_j1850",
    "load_layouts",
]

FLAG_SAT_A = 1
FLAG_SAT_B = 2
FLAG_STALE = 4
FLAG_PARK = 8


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc8_j1850(data: bytes | bytearray) -> int:
    """CRC-8 SAE J1850: poly 0x1D, init 0xFF, xor-out 0xFF (check value of b"123456789": 0x4B)."""
    crc = 0xFF
    for b in data:
        crc = _CRC_TABLE[crc ^ b]
    return crc ^ 0xFF


def frame_crc(frame_id: int, first7: bytes | bytearray) -> int:
    """The CRC signal of a frame: over the id (low, high byte) then data bytes 0-6."""
    return crc8_j1850(bytes((frame_id & 0xFF, (frame_id >> 8) & 0xFF)) + bytes(first7[:7]))


@dataclass(frozen=True)
class _Field:
    start: int
    length: int
    scale: float
    offset: float
    lo: int
    hi: int

    def raw(self, value: float) -> int:
        r = round((value - self.offset) / self.scale)
        return self.lo if r < self.lo else self.hi if r > self.hi else r


@dataclass(frozen=True)
class FrameLayout:
    """One setpoint frame, compiled from its DBC message."""

    frame_id: int
    name: str
    axes: tuple[str, str]
    axis_index: tuple[int, int]
    fields: tuple[_Field, _Field]
    flags: _Field
    alive: _Field
    crc: _Field

    def pack(self, positions: Sequence[float], flags: int, alive: int) -> bytes:
        """The 8 data bytes, CRC included."""
        a, b = self.fields
        word = ((a.raw(positions[self.axis_index[0]]) & ((1 << a.length) - 1)) << a.start
                | (b.raw(positions[self.axis_index[1]]) & ((1 << b.length) - 1)) << b.start
                | (flags & 0xF) << self.flags.start
                | (alive & 0xF) << self.alive.start)
        data = bytearray(word.to_bytes(8, "little"))
        data[self.crc.start // 8] = frame_crc(self.frame_id, data)
        return bytes(data)


def load_layouts(dbc_path: str | Path) -> tuple[list[FrameLayout], object]:
    """Compile the setpoint frames of a DBC file; returns ``(layouts, cantools database)``.

    Every axis must appear in exactly one message, as a little-endian signal named after it in
    capitals (``RAILS_X``); each such message also needs ``FLAGS`` (4 bit), ``ALIVE`` (4 bit) and
    ``CRC`` (8 bit, byte-aligned in byte 7).

    Raises
    ------
    ConfigError
        Naming the file, message and signal.
    """
    import cantools

    path = Path(dbc_path)
    try:
        db = cantools.database.load_file(str(path))
    except (OSError, cantools.database.UnsupportedDatabaseFormatError) as exc:
        raise ConfigError(f"{path}: cannot load DBC: {exc}") from None
    if not isinstance(db, cantools.database.can.Database):
        raise ConfigError(f"{path}: not a CAN database")
    names = {a.upper(): a for a in AXES}
    layouts: list[FrameLayout] = []
    seen: set[str] = set()
    for msg in db.messages:
        sigs = {s.name: s for s in msg.signals}
        axis_sigs = [s for s in msg.signals if s.name in names]
        if not axis_sigs:
            continue
        where = f"{path}: message {msg.name}"
        if len(axis_sigs) != 2:
            raise ConfigError(f"{where}: needs exactly two axis signals, has "
                              f"{[s.name for s in axis_sigs]}")
        for req, length in (("FLAGS", 4), ("ALIVE", 4), ("CRC", 8)):
            if req not in sigs or sigs[req].length != length:
                raise ConfigError(f"{where}: needs a {length}-bit signal {req}")
        if sigs["CRC"].start != 56:
            raise ConfigError(f"{where}: CRC must occupy byte 7 (start bit 56)")
        if msg.length != 8 or msg.is_extended_frame:
            raise ConfigError(f"{where}: must be a standard-id 8-byte frame")

        def field_of(sig: object, where: str = where) -> _Field:
            s = sig  # cantools Signal
            if s.byte_order != "little_endian":  # type: ignore[attr-defined]
                raise ConfigError(f"{where}: signal {s.name} must be little endian (@1)")  # type: ignore[attr-defined]
            length = s.length  # type: ignore[attr-defined]
            signed = s.is_signed  # type: ignore[attr-defined]
            lo, hi = (-(1 << (length - 1)), (1 << (length - 1)) - 1) if signed else (
                0, (1 << length) - 1)
            return _Field(s.start, length, float(s.scale), float(s.offset), lo, hi)  # type: ignore[attr-defined]

        axes = tuple(names[s.name] for s in axis_sigs)
        for a in axes:
            if a in seen:
                raise ConfigError(f"{where}: axis {a} appears in two messages")
            seen.add(a)
        layouts.append(FrameLayout(
            frame_id=msg.frame_id, name=msg.name, axes=(axes[0], axes[1]),
            axis_index=(AXES.index(axes[0]), AXES.index(axes[1])),
            fields=(field_of(axis_sigs[0]), field_of(axis_sigs[1])),
            flags=field_of(sigs["FLAGS"]), alive=field_of(sigs["ALIVE"]), crc=field_of(sigs["CRC"]),
        ))
    missing = [a for a in AXES if a not in seen]
    if missing:
        raise ConfigError(f"{path}: no message carries axis {missing[0]}")
    return layouts, db


def bus_load(frames_per_s: float, bitrate_bps: float = 1e6) -> tuple[float, float]:
    """``(best, worst)`` bus load fraction of standard 8-byte frames at ``frames_per_s``."""
    best = 111 + 3
    worst = 111 + 24 + 3
    return frames_per_s * best / bitrate_bps, frames_per_s * worst / bitrate_bps


def open_bus(interface: str, channel: str, bitrate_bps: int | None = None) -> object:
    """A python-can bus; library errors become :class:`TransportError`."""
    import can

    kwargs: dict[str, object] = {"interface": interface, "channel": channel}
    if bitrate_bps and interface not in ("virtual", "udp_multicast"):
        kwargs["bitrate"] = bitrate_bps
    if interface == "udp_multicast":
        kwargs["receive_own_messages"] = False
    try:
        return can.Bus(**kwargs)  # type: ignore[arg-type]
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise TransportError(f"cannot open CAN bus {interface}:{channel}: {exc}") from exc


def open_can_output(c: CanConfig, config_path: Path | None) -> CanSink:
    """The service's CAN output of ``c`` (``output.can``): its DBC (a relative path from the
    directory of ``config_path``, else among motcomp's shipped files) and its bus.

    Raises
    ------
    ConfigError
        A DBC that does not load or lacks an axis' frame.
    TransportError
        A bus that does not open here.
    """
    from motcomp.resources import config_file

    dbc = Path(c.dbc)
    if not dbc.is_absolute():
        base = config_path.parent if config_path else None
        dbc = base / dbc if base and (base / dbc).is_file() else config_file(c.dbc)
    layouts, _ = load_layouts(dbc)
    return CanSink(open_bus(c.interface, c.channel, c.bitrate_bps), layouts, c.send_every)


def check_can_output(c: CanConfig, config_path: Path | None) -> str:
    """``motcomp config check``'s CAN part: open the output as the service will, close it; the
    summary, or :class:`ConfigError` naming the bus and why (a bus that does not open here
    stops the service at start)."""
    try:
        sink = open_can_output(c, config_path)
    except TransportError as exc:
        raise ConfigError(f"output.can: {exc}: the service would not start here (exit 1); run "
                          "the check on the motion computer, where the bus is") from None
    sink.bus.shutdown()  # type: ignore[attr-defined]
    return (f"CAN: {c.interface}:{c.channel} opens ({len(sink.layouts)} frames of the DBC, "
            f"every {c.send_every} ticks)")


class CanSink:
    """Sends output frames on a CAN bus every ``send_every`` ticks, frames staggered.

    ``send(out, t)`` with a :class:`~motcomp.core.tick.TickOutput`; never blocks (``timeout=0``):
    a frame the driver cannot take is dropped and counted in :attr:`errors`.
    """

    def __init__(self, bus: object, layouts: list[FrameLayout], send_every: int = 1) -> None:
        import can

        self._can = can
        self.bus = bus
        self.layouts = layouts
        self.send_every = send_every
        self._per_tick = -(-len(layouts) // send_every)
        self._alive = [0] * len(layouts)
        self.sent = 0
        self.errors = 0
        self.last_error = ""

    def send(self, out: TickOutput, t: float = 0.0) -> None:
        """The frames of this tick's slot (an :class:`~motcomp.io.ports.OutputPort`; CAN frames
        carry no time, ``t`` is unused)."""
        slot = out.seq % self.send_every
        first = slot * self._per_tick
        positions, limited = out.u, out.limited
        base = (FLAG_STALE if out.mode == "stale" else 0) | (FLAG_PARK if out.mode == "parking"
                                                              else 0)
        for j in range(first, min(first + self._per_tick, len(self.layouts))):
            lay = self.layouts[j]
            flags = (base | (FLAG_SAT_A if limited[lay.axis_index[0]] else 0)
                     | (FLAG_SAT_B if limited[lay.axis_index[1]] else 0))
            self._alive[j] = (self._alive[j] + 1) & 0xF
            data = lay.pack(positions, flags, self._alive[j])
            msg = self._can.Message(arbitration_id=lay.frame_id, data=data, is_extended_id=False)
            try:
                self.bus.send(msg, timeout=0)  # type: ignore[attr-defined]
                self.sent += 1
            except self._can.CanError as exc:
                self.errors += 1
                self.last_error = str(exc)

    def close(self) -> None:
        self.bus.shutdown()  # type: ignore[attr-defined]


class CanSetpointReceiver:
    """The platform side: decodes setpoint frames (cantools), checks CRC and alive counter.

    :meth:`poll` drains the bus without blocking and returns the latest position of every axis
    received so far (a rejected frame changes nothing).
    """

    def __init__(self, bus: object, dbc_path: str | Path) -> None:
        self.bus = bus
        layouts, self.db = load_layouts(dbc_path)
        self._by_id = {lay.frame_id: lay for lay in layouts}
        self._alive: dict[int, int] = {}
        self.positions: dict[str, float] = {}
        self.flags: dict[str, int] = {}
        self.received = 0
        self.crc_errors = 0
        self.alive_errors = 0
        self.unknown = 0

    def check(self, frame_id: int, data: bytes) -> dict[str, float]:
        """Decoded signals of one frame.

        Raises
        ------
        FrameError
            ``crc``, ``alive`` or ``unknown`` frame.
        """
        lay = self._by_id.get(frame_id)
        if lay is None:
            raise FrameError("unknown", f"unknown CAN id 0x{frame_id:x}")
        if len(data) != 8 or data[7] != frame_crc(frame_id, data):
            raise FrameError("crc", f"CRC mismatch in frame 0x{frame_id:x}")
        decoded = self.db.get_message_by_frame_id(frame_id).decode(data)  # type: ignore[attr-defined]
        alive = int(decoded["ALIVE"])
        prev = self._alive.get(frame_id)
        self._alive[frame_id] = alive
        if prev is not None and alive != (prev + 1) & 0xF:
            raise FrameError("alive", f"alive counter of 0x{frame_id:x} went {prev} -> {alive}")
        return decoded

    def poll(self) -> dict[str, float]:
        while True:
            msg = self.bus.recv(timeout=0)  # type: ignore[attr-defined]
            if msg is None:
                return self.positions
            self.received += 1
            try:
                decoded = self.check(msg.arbitration_id, bytes(msg.data))
            except FrameError as exc:
                if exc.reason == "crc":
                    self.crc_errors += 1
                elif exc.reason == "alive":
                    self.alive_errors += 1
                    # the frame itself is valid: a lost frame is not a corrupt one
                    decoded = self.db.get_message_by_frame_id(  # type: ignore[attr-defined]
                        msg.arbitration_id).decode(bytes(msg.data))
                    self._apply(msg.arbitration_id, decoded)
                else:
                    self.unknown += 1
                continue
            self._apply(msg.arbitration_id, decoded)

    def _apply(self, frame_id: int, decoded: dict[str, float]) -> None:
        lay = self._by_id[frame_id]
        for axis in lay.axes:
            self.positions[axis] = float(decoded[axis.upper()])
            self.flags[axis] = int(decoded["FLAGS"])

    def close(self) -> None:
        self.bus.shutdown()  # type: ignore[attr-defined]
