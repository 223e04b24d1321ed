"""The tick compiled by mypyc and its plain Python source: which one runs, and that both give
the same outputs bit for bit (motcomp/core/native.py, docs/BENCHMARKS.md)."""

from __future__ import annotations

import importlib.machinery
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from motcomp.core import native

SUFFIX = importlib.machinery.EXTENSION_SUFFIXES[0]
MODULES = ("a", "b")


def fake_build(folder: Path) -> None:
    """Two modules, each with its source, an extension file and the build's record."""
    for m in MODULES:
        (folder / f"{m}.py").write_text(f"X = {m!r}\n")
        (folder / f"{m}{SUFFIX}").write_bytes(b"")
    (folder / native.RECORD).write_text(json.dumps(native.source_hashes(folder, MODULES)))


def test_the_compiled_modules_are_used_only_all_present_and_built_from_their_source(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(native.PURE_ENV, raising=False)
    fake_build(tmp_path)
    assert native.verdict(tmp_path, MODULES) == ""
    monkeypatch.setenv(native.PURE_ENV, "1")
    assert native.PURE_ENV in native.verdict(tmp_path, MODULES)
    monkeypatch.setenv(native.PURE_ENV, "0")
    assert native.verdict(tmp_path, MODULES) == ""
    (tmp_path / "b.py").write_text("X = 'edited'\n")
    assert "source changed since the build: b" in native.verdict(tmp_path, MODULES)
    fake_build(tmp_path)
    (tmp_path / f"a{SUFFIX}").unlink()
    assert native.verdict(tmp_path, MODULES) == "compiled modules missing: a"
    (tmp_path / f"b{SUFFIX}").unlink()
    assert native.verdict(tmp_path, MODULES) == "not compiled at install"
    fake_build(tmp_path)
    (tmp_path / native.RECORD).unlink()
    assert "no record of the compiled sources" in native.verdict(tmp_path, MODULES)


def test_plain_python_is_loaded_from_the_source_beside_a_stale_extension(tmp_path: Path) -> None:
    """A package whose 'compiled' module is a broken file and whose source changed: the
    plain source is what imports (the broken extension would raise if it were loaded)."""
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    fake_build(pkg)
    (pkg / "a.py").write_text("X = 'the source'\n")
    (pkg / "__init__.py").write_text("")
    code = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        sys.path.insert(0, {str(tmp_path)!r})
        from motcomp.core import native
        print(native.choose("fakepkg", Path({str(pkg)!r}), {MODULES!r}))
        import fakepkg.a, fakepkg.b
        print(fakepkg.a.X, fakepkg.b.X)
    """)
    env = {k: v for k, v in os.environ.items() if k != native.PURE_ENV}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    active, values = p.stdout.splitlines()
    assert active.startswith("plain Python (source changed since the build: a")
    assert values == "the source b"


REPLAY = textwrap.dedent("""
    import json, sys
    import numpy as np
    from motcomp.config import load_config, resolve_axes
    from motcomp.core import native
    from motcomp.record import read_session
    from motcomp.replay.engine import run_ticks
    from motcomp.replay.offline import plan_for
    from motcomp.resources import config_file
    cfg = load_config(config_file("motcomp.toml"))
    s = read_session(sys.argv[1])
    plan = plan_for(s, cfg, resolve_axes(cfg))
    res = run_ticks(plan, s.inputs, cfg)
    rows = np.flatnonzero(plan.output >= 0)
    rec = s.outputs.pos[plan.output[rows]]
    print(json.dumps({"active": native.ACTIVE, "rows": int(rows.size),
                      "equal": bool(np.array_equal(res.u[rows], rec)),
                      "max_diff": float(np.abs(res.u[rows] - rec).max())}))
""")


def test_compiled_and_plain_python_ticks_agree_bit_for_bit(tmp_path: Path) -> None:
    """A synthetic session written by the compiled tick (jittered and stalled input, a gap,
    bypass switches, a step, bad and partial frames, parking) replayed by the plain Python
    one: every output equal, bit for bit."""
    if not native.ACTIVE.startswith("compiled"):
        pytest.skip(f"the tick is not compiled here: {native.ACTIVE}")
    from motcomp.config import load_config
    from motcomp.replay.synth import SynthOptions, synthesize
    from motcomp.resources import config_file

    path = tmp_path / "rich.mcap"
    synthesize(path, load_config(config_file("motcomp.toml")),
               SynthOptions(duration_s=20.0, seed=11, stalls=[(4.5, 3), (9.0, 30)],
                            gaps=[(6.0, 0.4)], bypass=[(8.0, True, ("rails_x",)),
                                                       (12.0, False, ("rails_x",))],
                            steps=[(14.0, "rails_y", 0.3)], partial_every=7, bad_every=97,
                            no_t_every=13, park_at_s=18.0))
    env = {**os.environ, native.PURE_ENV: "1"}
    p = subprocess.run([sys.executable, "-c", REPLAY, str(path)], capture_output=True,
                       text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["active"] == f"plain Python ({native.PURE_ENV} is set)"
    assert out["rows"] > 19_000
    assert out["equal"], out
