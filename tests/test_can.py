"""CAN output: the compiled packer against cantools, CRC, and real python-can buses."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from motcomp.core.axes import AXES
from motcomp.core.tick import TickOutput
from motcomp.errors import ConfigError, FrameError
from motcomp.io.can_io import (
    CanSetpointReceiver,
    CanSink,
    bus_load,
    crc8_j1850,
    frame_crc,
    load_layouts,
)
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env

DBC = config_file("motcomp.dbc")
LAYOUTS, DB = load_layouts(DBC)


def test_crc8_check_value() -> None:
    # SAE J1850 CRC-8 catalogue check value
    assert crc8_j1850(b"123456789") == 0x4B


@given(pos=st.lists(st.floats(-8.3, 8.3), min_size=8, max_size=8),
       flags=st.integers(0, 15), alive=st.integers(0, 15))
def test_compiled_packer_equals_cantools(pos: list[float], flags: int, alive: int) -> None:
    for lay in LAYOUTS:
        data = lay.pack(pos, flags, alive)
        msg = DB.get_message_by_frame_id(lay.frame_id)  # type: ignore[attr-defined]
        a, b = lay.axes
        ref = msg.encode({a.upper(): pos[AXES.index(a)], b.upper(): pos[AXES.index(b)],
                          "FLAGS": flags, "ALIVE": alive, "CRC": data[7]})
        assert data == ref
        assert data[7] == frame_crc(lay.frame_id, data)
        dec = msg.decode(data)
        assert dec[a.upper()] == pytest.approx(pos[AXES.index(a)], abs=0.6e-6)


def test_every_axis_in_one_frame() -> None:
    assert sorted(a for lay in LAYOUTS for a in lay.axes) == sorted(AXES)
    assert {lay.frame_id for lay in LAYOUTS} == {0x100, 0x101, 0x102, 0x103}


def test_bus_load_of_the_layout() -> None:
    best, worst = bus_load(4 * 1000)  # 4 frames per cycle at 1 kHz
    assert best == pytest.approx(0.456) and worst == pytest.approx(0.552)
    assert bus_load(4 * 250)[1] < 0.14


def test_bad_dbc_rejected(tmp_path) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad.dbc"
    bad.write_text(DBC.read_text().replace("SG_ CRC : 56|8@1+", "SG_ CRC : 56|4@1+", 1))
    with pytest.raises(ConfigError, match="MOTCOMP_SP_RAILS: needs a 8-bit signal CRC"):
        load_layouts(bad)
    overlap = tmp_path / "overlap.dbc"
    overlap.write_text(DBC.read_text().replace("SG_ CRC : 56|8@1+", "SG_ CRC : 48|8@1+", 1))
    with pytest.raises(ConfigError, match=r"cannot load DBC.*overlapping"):
        load_layouts(overlap)
    missing = tmp_path / "missing.dbc"
    missing.write_text(DBC.read_text().replace("HEX_YAW", "HEX_YAWN"))
    with pytest.raises(ConfigError, match="HEX_PITCH_YAW: needs exactly two axis signals"):
        load_layouts(missing)


def test_virtual_bus_round_trip_staggered_with_alive_and_crc() -> None:
    tx = can.Bus(interface="virtual", channel="motcomp-test-rt", receive_own_messages=False)
    rx = can.Bus(interface="virtual", channel="motcomp-test-rt")
    sink = CanSink(tx, LAYOUTS, send_every=4)
    recv = CanSetpointReceiver(rx, DBC)
    try:
        for tick in range(40):
            pos = [0.001 * tick * (i + 1) for i in range(8)]
            sink.send(TickOutput(tick, -1, pos, [], [i == 1 for i in range(8)], ""), 0.0)
            got = recv.poll()
            lay = LAYOUTS[tick % 4]  # one frame per tick, in turn
            for a in lay.axes:
                assert got[a] == pytest.approx(pos[AXES.index(a)], abs=1e-6)
        assert sink.sent == 40 and recv.received == 40
        assert recv.crc_errors == 0 and recv.alive_errors == 0
        assert recv.flags["rails_y"] & 2 and not recv.flags["hex_x"] & 3
        # a corrupted frame is rejected by its CRC and changes nothing
        before = dict(recv.positions)
        data = bytearray(LAYOUTS[0].pack([1.0] * 8, 0, 7))
        data[1] ^= 0x40
        tx.send(can.Message(arbitration_id=0x100, data=bytes(data), is_extended_id=False))
        assert recv.poll() == before and recv.crc_errors == 1
        with pytest.raises(FrameError, match="unknown CAN id"):
            recv.check(0x7FF, bytes(8))
    finally:
        sink.close()
        recv.close()


def test_lost_frame_counts_an_alive_error_but_keeps_the_value() -> None:
    tx = can.Bus(interface="virtual", channel="motcomp-test-alive", receive_own_messages=False)
    rx = can.Bus(interface="virtual", channel="motcomp-test-alive")
    recv = CanSetpointReceiver(rx, DBC)
    lay = LAYOUTS[0]
    try:
        for alive in (1, 2, 4):  # 3 lost
            tx.send(can.Message(arbitration_id=lay.frame_id,
                                data=lay.pack([alive / 10] * 8, 0, alive), is_extended_id=False))
        recv.poll()
        assert recv.alive_errors == 1
        assert math.isclose(recv.positions["rails_x"], 0.4, abs_tol=1e-6)
    finally:
        tx.shutdown()
        recv.close()


@pytest.mark.parametrize(("can_table", "code", "says"), [
    ('interface = "udp_multicast"\nchannel = "239.74.163.91"', 0,
     "CAN: udp_multicast:239.74.163.91 opens (4 frames of the DBC, every 4 ticks)"),
    ('interface = "socketcann"', 2,
     "output.can.interface: not a python-can interface; did you mean 'socketcan'?"),
    ('interface = "virtual"\nchannel = "x"\ndbc = "nosuch.dbc"', 2, "nosuch.dbc"),
])
def test_config_check_opens_the_can_output_as_the_service_will(
        tmp_path: Path, can_table: str, code: int, says: str) -> None:
    """``config check`` of a config whose output goes over CAN opens it as the service will:
    the interface must be python-can's, the DBC must load and the bus open here (where a bus
    does not open, the service would not start)."""
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[output]\ntransport = "can"\n'
                    f"[output.can]\n{can_table}\n")
    p = subprocess.run(motcomp_cmd("config", "check", str(site)), capture_output=True,
                       text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == code and says in p.stdout + p.stderr, p.stdout + p.stderr


@pytest.mark.skipif(Path("/sys/class/net/can0").exists(), reason="this machine has a can0")
def test_config_check_says_when_the_bus_does_not_open_here(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[output]\ntransport = "both"\n'
                    '[output.can]\ninterface = "socketcan"\nchannel = "can0"\n')
    p = subprocess.run(motcomp_cmd("config", "check", str(site)), capture_output=True,
                       text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 2, p.stdout + p.stderr
    assert "output.can: cannot open CAN bus socketcan:can0" in p.stderr
    assert "the service would not start here" in p.stderr
