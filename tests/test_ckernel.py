"""The compiled tick (motcomp/core/_ckernel.c) against the Python reference: bit for bit.

Both kernels step the same state buffers with the same floating-point operations in the same
order, so every command, flag and state variable must be *equal*, not close: through
saturation of every kind, non-finite references, bypass fades, live gain/model/limit changes,
resets and the wrap-around of the delay line.
"""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import fields

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core import compensator as compmod
from motcomp.core.axes import AXES
from motcomp.core.compensator import Compensator, default_kernel
from motcomp.core.models import P1D
from motcomp.core.pid import PIDGains
from motcomp.core.saturation import AxisLimits
from motcomp.core.tuning import tune
from motcomp.errors import ConfigError
from tests.conftest import subprocess_env

pytestmark = pytest.mark.skipif(compmod._ckernel is None,
                                reason="the compiled kernel is not built")

RAILS = P1D(K=1.0, Td=0.0175, Tp1=0.1858)
HEX = P1D(K=1.0, Td=0.0325, Tp1=0.0025)
LIMITS = AxisLimits([-2.6, -2.6, -0.2, -0.2, -0.2, -0.3, -0.3, -0.4],
                    [2.6, 2.6, 0.2, 0.2, 0.2, 0.3, 0.3, 0.4],
                    [2.0, 2.0, 0.5, 0.5, 0.5, 0.8, 0.8, 0.8],
                    [6.0, 6.0, 5.0, 5.0, 5.0, 8.0, 8.0, 8.0], names=AXES)


def _pair(rate_hz: float = 1000.0, rule: str = "zn", weights: bool = True
          ) -> tuple[Compensator, Compensator]:
    models = [RAILS, RAILS] + [HEX] * 6
    gains = [tune(rule, m).gains for m in models]
    if weights:
        gains = [PIDGains(g.kp, g.ki, g.kd, g.tf, b=1.1, c=2.3) for g in gains]
    return tuple(Compensator(models, gains, LIMITS, rate_hz, fade_s=0.2, history_s=0.1,
                             kernel=k) for k in ("c", "python"))  # type: ignore[return-value]


def _same_state(a: Compensator, b: Compensator) -> None:
    sa, sb = a.state(), b.state()
    for f in fields(sa):
        x, y = getattr(sa, f.name), getattr(sb, f.name)
        assert np.array_equal(x, y), f.name
    assert list(a.deviation) == list(b.deviation)
    assert a.flags == b.flags


def _references(n: int, seed: int) -> np.ndarray:
    """Slow sines within the limits, sample jitter, 0.4 m steps and bursts far beyond the
    limits (position, velocity and acceleration saturation, braking at the end stops)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 1000.0
    amp = np.array([2.0, 2.0, 0.15, 0.15, 0.15, 0.25, 0.25, 0.3])
    ref = amp * np.sin(2 * math.pi * np.outer(t, [0.2, 0.5, 1, 2, 3, 0.7, 1.3, 0.1]))
    ref += rng.normal(0, 1e-4, ref.shape)
    ref[n // 3:, 0] += 0.4
    burst = rng.random(ref.shape) < 0.002
    ref[burst] *= 3.0
    return ref


def test_bit_identical_through_saturation_and_delay_line_wrap() -> None:
    c, p = _pair()
    ref = _references(3000, 1)  # 3000 samples: the 128-slot delay line wraps many times
    for row in ref.tolist():
        assert c.step(row) == p.step(row)
        assert c.flags == p.flags
    flags_seen = np.array(c.run(ref)[1])
    p.run(ref)
    assert (flags_seen != 0).any()  # the limiter acted
    _same_state(c, p)


@pytest.mark.parametrize("rule", ["zn", "cc", "amigo"])
def test_bit_identical_with_bypass_nonfinite_and_live_changes(rule: str) -> None:
    c, p = _pair(rule=rule, weights=rule != "amigo")
    ref = _references(2500, 7)
    ref[100:105, 2] = np.nan
    ref[200, 3] = np.inf
    ref[300:302, 0] = -np.inf
    new_gains = [tune("amigo", m).gains for m in [RAILS, RAILS] + [HEX] * 6]
    narrow = AxisLimits(LIMITS.p_min * 0.5, LIMITS.p_max * 0.5, LIMITS.v_max, LIMITS.a_max,
                        names=AXES)
    for k, row in enumerate(ref.tolist()):
        for comp in (c, p):
            if k == 400:
                comp.set_bypass([True, False, True, False, False, False, False, True])
            elif k == 900:
                comp.set_bypass([False] * 8)
            elif k == 1200:
                comp.set_gains(new_gains)
            elif k == 1500:
                comp.set_models([P1D(K=1.0, Td=0.02, Tp1=0.17)] * 2 + [HEX] * 6)
            elif k == 1800:
                comp.set_limits(narrow)  # axes left outside the new range brake back in
            elif k == 2200:
                comp.reset([0.1] * 8)
        assert c.step(row) == p.step(row), k
        assert c.flags == p.flags, k
    _same_state(c, p)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.floats(-5.0, 5.0), min_size=8, max_size=8), min_size=1,
                max_size=60),
       st.sampled_from([333.0, 1000.0, 2000.0]),
       st.lists(st.booleans(), min_size=8, max_size=8))
def test_bit_identical_on_arbitrary_references(rows: list[list[float]], rate_hz: float,
                                               bypass: list[bool]) -> None:
    c, p = _pair(rate_hz=rate_hz)
    for comp in (c, p):
        comp.set_bypass(bypass)
    for row in rows:
        assert c.step(row) == p.step(row)
        assert c.flags == p.flags
    _same_state(c, p)


def test_kernel_checks_its_input() -> None:
    c, _ = _pair()
    with pytest.raises(ValueError, match="7 values for 8 axes"):
        c.step([0.0] * 7)
    with pytest.raises(TypeError):
        c.step(["x"] * 8)  # type: ignore[list-item]
    _same_state(c, _pair()[1])  # nothing changed
    with pytest.raises(ConfigError, match="unknown compensator kernel"):
        Compensator([RAILS], [PIDGains(1.0, 1.0)], AxisLimits.uniform(1, 1, 1, 1), 1000.0,
                    kernel="fortran")


def test_stepper_rejects_wrong_buffers() -> None:
    from array import array

    from motcomp.core._ckernel import Stepper

    good = [array("d", [0.0])] * 13 + [array("d", [0.0] * 3), array("d", [0.0] * 4),
                                       array("d", [0.0] * 4), array("d", [0.0] * 6),
                                       array("d", [0.0] * 3), array("d", [0.0] * 24),
                                       array("q", [0, 0]), array("b", [0])]
    Stepper(1, 4, good)
    with pytest.raises(ValueError, match="buffer offsets"):
        Stepper(1, 4, [*good[:19], array("d", [0.0, 0.0]), *good[20:]])
    with pytest.raises(ValueError, match="buffer hist_c"):
        Stepper(1, 4, [*good[:14], array("d", [0.0] * 3), *good[15:]])
    with pytest.raises(ValueError, match="power-of-two"):
        Stepper(1, 3, good)
    with pytest.raises(ValueError, match="21 buffers"):
        Stepper(1, 4, good[:5])


def test_default_kernel_follows_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("MOTCOMP_KERNEL", raising=False)
    assert default_kernel() == "c"
    monkeypatch.setenv("MOTCOMP_KERNEL", "python")
    assert default_kernel() == "python"
    assert _pair()[0].kernel == "c"  # an explicit choice wins
    monkeypatch.setenv("MOTCOMP_KERNEL", "rust")
    with pytest.raises(ConfigError, match="MOTCOMP_KERNEL='rust'"):
        default_kernel()


def test_without_the_compiled_kernel_the_python_one_runs() -> None:
    """What an install without a C compiler gets: the import fails, the Python kernel runs."""
    code = ("import sys; sys.modules['motcomp.core._ckernel'] = None\n"
            "from motcomp.core.compensator import Compensator, default_kernel\n"
            "from motcomp.core.saturation import AxisLimits\n"
            "from motcomp.core.models import P1D\nfrom motcomp.core.pid import PIDGains\n"
            "c = Compensator([P1D(1, 0.01, 0.2)], [PIDGains(2.0, 10.0)],"
            " AxisLimits.uniform(1, 1, 1, 10), 1000.0)\n"
            "print(default_kernel(), c.kernel, c.step([0.001]))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=subprocess_env(), timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[:2] == ["python", "python"]


def test_service_reports_its_kernels() -> None:
    """The status' "kernel": "c" with everything built, "python" when asked for."""
    code = ("from motcomp.config import load_config\nfrom motcomp.resources import config_file\n"
            "from motcomp.io.zenoh_io import ZenohEndpoints\n"
            "from motcomp.runtime.service import Service\n"
            "print(Service(load_config(config_file('motcomp.toml')), ZenohEndpoints()).kernels())")
    for env, want in (({}, "c"), ({"MOTCOMP_KERNEL": "python"}, "python")):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env={**subprocess_env(), **env}, timeout=60)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == want
