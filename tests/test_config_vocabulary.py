"""One vocabulary from identification to the service config (issue 15, point 3):
``identify`` writes ``<axis>.toml``, ``design --plant <axis>.toml --out design.toml`` reads it and
writes the gains in the config's keys, the site config includes both, and ``config check`` says
where every axis' model and gains come from and warns when an included one is lost."""

from __future__ import annotations

import json
import re
import subprocess
import tomllib
from pathlib import Path

import pytest

from motcomp.config import (
    config_sources,
    load_config,
    merge,
    read_toml,
    resolve_axes,
    source_report,
)
from motcomp.core.models import parse_model
from motcomp.core.pid import PIDGains
from motcomp.errors import ConfigError
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env

EXAMPLE = config_file("motcomp.toml")
IDENTIFIED = "p1d:K=0.9914865737,Td=0.01749696406,Tp1=0.1840670684"
# the format of motcomp.ident.report.config_fragment
FRAGMENT = f"""# Identified by motcomp identify from session.mcap
# (60.0 s at 1000 Hz; prefilter 8 Hz).
# Selected p1d: validation fit 93.54 %, VAF 99.58 %, AIC -19348.4.
# Pure delay 17.50 ms, phase delay at 0.2 Hz 198.4 ms, bandwidth -3 dB 0.865 Hz, -6 dB 1.5 Hz.
# Also fitted: p2d:K=0.99,Td=0.0172,Tp1=0.184,Tp2=0.0011 (validation fit 93.50 %, AIC -19340.1)
[axes.rails_y]
model = "{IDENTIFIED}"
"""

LIMITS = "pos_min_m = -1.5\npos_max_m = 1.5\nvel_max_m_s = 1.0\nacc_max_m_s2 = 4.0\n"


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=300, cwd=cwd)


def axis_gains(path: Path, axis: str) -> PIDGains:
    axes = resolve_axes(load_config(path))
    return axes.gains[axes.names.index(axis)]


@pytest.fixture
def designed(tmp_path: Path) -> tuple[Path, dict]:
    """``rails_y.toml`` as identify writes it, and ``design.toml`` designed from it (ZN)."""
    (tmp_path / "rails_y.toml").write_text(FRAGMENT)
    p = run("design", "--plant", "rails_y.toml", "--rule", "zn", "--out", "design.toml",
            "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "wrote design.toml" in p.stderr
    return tmp_path, json.loads(p.stdout)


def test_design_reads_the_identified_fragment(designed: tuple[Path, dict]) -> None:
    _, report = designed
    assert report["model_spec"] == IDENTIFIED  # a P1D is its own internal model
    by_spec = run("design", "--model", IDENTIFIED, "--rule", "zn", "--json")
    assert json.loads(by_spec.stdout)["gains"] == report["gains"]


def test_design_fragment_uses_the_config_keys(designed: tuple[Path, dict]) -> None:
    d, report = designed
    text = (d / "design.toml").read_text()
    assert text.startswith("# motcomp design: zn, rails_y.toml, 1000 Hz: residual ")
    assert "(generated)" in text.splitlines()[0]
    table = tomllib.loads(text)
    assert list(table) == ["axes"] and list(table["axes"]) == ["rails_y"]
    axis = table["axes"]["rails_y"]
    assert axis == {"model": IDENTIFIED, "bypass": False, "gains": report["gains"],
                    "predict": False}  # no prefilter in this design: an inherited one unused
    assert set(axis["gains"]) == {"kp", "ki_per_s", "kd_s", "tf_s", "b", "c"}


def test_site_config_including_example_and_design_runs_the_designed_gains(
        designed: tuple[Path, dict]) -> None:
    d, report = designed
    site = d / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}", "rails_y.toml", "design.toml"]\n')
    chk = run("config", "check", str(site))
    assert chk.returncode == 0, chk.stderr
    gains = tomllib.loads((d / "design.toml").read_text())["axes"]["rails_y"]["gains"]
    assert axis_gains(site, "rails_y") == PIDGains.from_config(gains)
    assert axis_gains(site, "rails_y") == PIDGains.from_config(report["gains"])  # exact floats
    cfg = load_config(site)
    assert cfg.axes["rails_y"].model == IDENTIFIED and cfg.axes["rails_y"].bypass is False
    assert axis_gains(site, "rails_x") == axis_gains(EXAMPLE, "rails_x")  # the rest untouched
    lines, warnings = source_report(site)
    # the example's rails carry a prefilter designed with its own gains; a PID-only design
    # switches it off for the axis it writes (predict = false)
    assert ("  rails_y    model from design.toml, gains from design.toml, prediction from "
            f"{EXAMPLE}, UNUSED (predict = false from design.toml)") in lines
    assert (f"  rails_x    model from {EXAMPLE}, gains from {EXAMPLE}, prediction from "
            f"{EXAMPLE}") in lines
    assert load_config(site).axes["rails_y"].predict is False
    assert warnings == []


def test_design_fragment_shadowed_by_the_including_file_is_reported(
        designed: tuple[Path, dict]) -> None:
    """The example copied as the site config with the design included at its top: the copy's own
    ``model`` and ``gains`` lines win over the design (includes are merged underneath)."""
    d, _ = designed
    site = d / "site.toml"
    site.write_text('include = ["design.toml"]\n' + EXAMPLE.read_text())
    assert run("config", "check", str(site)).returncode == 0
    assert axis_gains(site, "rails_y") == axis_gains(EXAMPLE, "rails_y")
    _, warnings = source_report(site)
    shadowed = {w.split(" ", 2)[1]: w for w in warnings}
    assert set(shadowed) == {"axes.rails_y.model", "axes.rails_y.gains"}
    w = shadowed["axes.rails_y.model"]
    assert "from design.toml" in w and "overridden by site.toml" in w and IDENTIFIED in w
    assert w.endswith("delete axes.rails_y.model from site.toml")


def test_identified_model_under_the_example_is_reported(tmp_path: Path) -> None:
    """The fragment listed before the example: the example's model wins."""
    (tmp_path / "rails_y.toml").write_text(FRAGMENT)
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["rails_y.toml", "{EXAMPLE}"]\n')
    assert load_config(site).axes["rails_y"].model != IDENTIFIED
    _, warnings = source_report(site)
    assert len(warnings) == 1
    assert warnings[0].startswith(f'warning: axes.rails_y.model from rails_y.toml ("{IDENTIFIED}")'
                                  f" is overridden by {EXAMPLE}")
    assert warnings[0].endswith(f"include rails_y.toml after {EXAMPLE}")


def test_identified_model_with_the_examples_gains_is_reported(tmp_path: Path) -> None:
    (tmp_path / "rails_y.toml").write_text(FRAGMENT)
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}", "rails_y.toml"]\n')
    lines, warnings = source_report(site)
    assert (f"  rails_y    model from rails_y.toml, gains from {EXAMPLE}, prediction from "
            f"{EXAMPLE}") in lines
    assert len(warnings) == 1 and "gains designed for another model" in warnings[0]
    assert "motcomp design --plant rails_y.toml --axis rails_y --out FILE" in warnings[0]


def test_commented_out_include_is_reported(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text('# include = ["identified.toml"]  # the identified model\n'
                    + EXAMPLE.read_text())
    _, warnings = source_report(site)
    assert warnings == [
        'warning: site.toml:1: include is commented out (# include = ["identified.toml"]  # the '
        "identified model): identified.toml is not read, so no model or gains of it are used"]
    # the example itself says how to include, without a commented-out include line
    site.write_text(EXAMPLE.read_text())
    assert source_report(site)[1] == []
    # the example included (not copied): its commented line is documentation, unless the file
    # it names exists
    site.write_text(f'include = ["{EXAMPLE}"]\n')
    assert source_report(site)[1] == []
    inc = tmp_path / "inc" / "base.toml"
    inc.parent.mkdir()
    inc.write_text('# include = ["rails_y.toml"]\n' + f'include = ["{EXAMPLE}"]\n')
    (inc.parent / "rails_y.toml").write_text(FRAGMENT)
    site.write_text('include = ["inc/base.toml"]\n')
    (w,) = source_report(site)[1]
    assert w.startswith("warning: inc/base.toml:1: include is commented out") and "exists" in w


def test_bypass_recommendation_writes_bypass_without_gains(tmp_path: Path) -> None:
    p = run("design", "--plant", "hexapod", "--rule", "zn", "--axis", "hex_z", "--out",
            str(tmp_path / "hex.toml"), "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["recommendation"] == "bypass"
    axis = tomllib.loads((tmp_path / "hex.toml").read_text())["axes"]["hex_z"]
    assert axis == {"model": "p2uzd:K=1,Td=0.0325,Tw=0.06399186527,Zeta=0.7,Tz=0.08764049978",
                    "bypass": True, "predict": False}
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}", "hex.toml"]\n')
    assert run("config", "check", str(site)).returncode == 0
    axes = resolve_axes(load_config(site))
    assert axes.bypass[axes.names.index("hex_z")]


def test_human_output_ends_with_the_fragment(tmp_path: Path) -> None:
    (tmp_path / "rails_y.toml").write_text(FRAGMENT)
    p = run("design", "--plant", "rails_y.toml", "--rule", "amigo", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    m = re.search(r"```toml\n(.*)```\n\Z", p.stdout, re.S)
    assert m is not None, p.stdout[-500:]
    table = tomllib.loads(m.group(1))
    assert list(table["axes"]) == ["rails_y"] and table["axes"]["rails_y"]["model"] == IDENTIFIED
    assert not (tmp_path / "design.toml").exists()


def test_several_axes_need_axis(tmp_path: Path) -> None:
    frag = tmp_path / "axes.toml"
    frag.write_text(FRAGMENT + '\n[axes.rails_x]\nmodel = "p1d:K=1,Td=0.02,Tp1=0.15"\n')
    p = run("design", "--plant", str(frag), "--rule", "zn")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert f"{frag}: axes: holds rails_y, rails_x; choose one with --axis NAME" in p.stderr
    p = run("design", "--plant", str(frag), "--axis", "rails_x", "--rule", "zn", "--json")
    assert p.returncode == 0 and json.loads(p.stdout)["model_spec"] == "p1d:K=1,Td=0.02,Tp1=0.15"


@pytest.mark.parametrize(("text", "axis", "msg"), [
    ('[axes.rails_y]\nmodel = "p1d:K=1,Td=0.01"\n', None,
     "axes.rails_y.model: model spec 'p1d:K=1,Td=0.01': missing parameter(s) Tp1"),
    ('[axes.rails_y]\nmodle = "p1d:K=1,Td=0.01,Tp1=0.1"\n', None,
     "axes.rails_y.modle: unknown key 'modle'; did you mean 'model'?"),
    ("[axes.rails_y]\nbypass = true\n", None, "axes.rails_y.model: missing"),
    (FRAGMENT, "hex_x", "axes.hex_x: no such table; axes in the file: rails_y"),
    (FRAGMENT + "pos_min_m = -1\n", None, "axes.rails_y: limits of rails_y: missing pos_max_m"),
    ("[axes.rails_y\n", None, "not valid TOML"),
])
def test_bad_fragment_names_file_and_key(tmp_path: Path, text: str, axis: str | None,
                                         msg: str) -> None:
    frag = tmp_path / "f.toml"
    frag.write_text(text)
    p = run("design", "--plant", str(frag), *(["--axis", axis] if axis else []))
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert str(frag) in p.stderr and msg in p.stderr, p.stderr


def test_fragment_limits_reach_evaluate(tmp_path: Path) -> None:
    from motcomp.presets import plant_source

    frag = tmp_path / "f.toml"
    frag.write_text(FRAGMENT + LIMITS)
    src = plant_source(str(frag))
    assert (src.axis, src.label, src.model) == ("rails_y", "f.toml", parse_model(IDENTIFIED))
    assert src.limits is not None and src.limits.names == ("rails_y",)
    assert (float(src.limits.p_max[0]), float(src.limits.a_max[0])) == (1.5, 4.0)
    assert plant_source("rails").limits is not None
    assert plant_source(model=IDENTIFIED).limits is None


# --- the include merge and its provenance ------------------------------------------------------

def test_gains_table_is_replaced_whole() -> None:
    """A hand-written plain PID over a design with setpoint weights does not keep its b, c."""
    base = {"axes": {"rails_y": {"model": "m", "gains": {"kp": 8.0, "b": 1.1, "c": 2.3}}}}
    over = {"axes": {"rails_y": {"gains": {"kp": 12.7, "ki_per_s": 364.0}}}}
    assert merge(base, over) == {"axes": {"rails_y": {
        "model": "m", "gains": {"kp": 12.7, "ki_per_s": 364.0}}}}


def test_rule_and_gains_displace_each_other(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text(FRAGMENT + "gains = { kp = 10.0 }\n" + LIMITS)
    site = tmp_path / "site.toml"
    site.write_text('include = ["base.toml"]\n[axes.rails_y]\nrule = "amigo"\n')
    data = read_toml(site)
    assert data["axes"]["rails_y"] == {"model": IDENTIFIED, "rule": "amigo",
                                       **tomllib.loads(LIMITS)}
    src = config_sources(site)
    assert src.sources["axes.rails_y.rule"] == site.resolve()
    assert src.sources["axes.rails_y.model"] == (tmp_path / "base.toml").resolve()
    assert "axes.rails_y.gains" not in src.sources
    (o,) = src.overrides
    assert (o.key, o.upper_key, o.lower_value, o.upper_value) == (
        "axes.rails_y.gains", "axes.rails_y.rule", {"kp": 10.0}, "amigo")
    (w,) = source_report(site)[1]
    assert "axes.rails_y.gains from base.toml" in w and "axes.rails_y.rule in site.toml" in w


def test_sources_follow_the_include_order(tmp_path: Path) -> None:
    (tmp_path / "a.toml").write_text("[loop]\nrate_hz = 500\nhold_s = 1.0\n")
    (tmp_path / "b.toml").write_text('include = "a.toml"\n[loop]\nrate_hz = 800\n')
    top = tmp_path / "top.toml"
    top.write_text('include = ["b.toml"]\n[loop]\nhold_s = 2.0\n')
    src = config_sources(top)
    a, b, t = (tmp_path / n for n in ("a.toml", "b.toml", "top.toml"))
    assert src.files == (a, b, t)
    assert src.parents == {b: t, a: b}
    assert src.sources == {"loop.rate_hz": b, "loop.hold_s": t}
    assert [(o.key, o.lower.name, o.upper.name) for o in src.overrides] == [
        ("loop.rate_hz", "a.toml", "b.toml"), ("loop.hold_s", "a.toml", "top.toml")]
    assert read_toml(top) == {"loop": {"rate_hz": 800, "hold_s": 2.0}}
    assert src.fragments == frozenset()  # fragments hold only [axes.*]


@pytest.mark.slow
def test_identify_design_include_check(tmp_path: Path) -> None:
    """The documented workflow, no number edited by hand: a platform unlike the example's."""
    platform = "p1d:K=1,Td=0.025,Tp1=0.15"
    assert run("excite", "--axis", "rails_y", "--kind", "noise", "--duration", "30",
               "--seed", "3", "--out", str(tmp_path / "x"), "--simulate", platform,
               "--snr", "20").returncode == 0
    p = run("identify", str(tmp_path / "x.sim.csv"), "--axis", "rails_y", "--models", "p1d",
            "--out", str(tmp_path / "ident"), "--no-figures", "--json", "--quiet")
    assert p.returncode == 0, p.stderr
    identified = json.loads(p.stdout)["model_spec"]
    frag = tmp_path / "ident" / "rails_y.toml"
    p = run("design", "--plant", str(frag), "--rule", "zn", "--out",
            str(tmp_path / "design.toml"), "--json")
    assert p.returncode == 0, p.stderr
    gains = json.loads(p.stdout)["gains"]
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}", "ident/rails_y.toml", "design.toml"]\n')
    chk = run("config", "check", str(site))
    assert chk.returncode == 0, chk.stderr
    cfg = load_config(site)
    assert cfg.axes["rails_y"].model == identified
    assert axis_gains(site, "rails_y") == PIDGains.from_config(gains)
    assert source_report(site)[1] == []


@pytest.mark.parametrize(("text", "msg"), [
    ("[loop]\nrate_hx = 1000\n", "loop.rate_hx: unknown key 'rate_hx'; did you mean 'rate_hz'?"),
    ("[envelope.rails_y]\npos_max = 1\n",
     "envelope.rails_y.pos_max: unknown key 'pos_max'; did you mean 'pos_max_m'"),
    ('profle = "fast"\n', "profle: unknown key 'profle'; did you mean 'profile' or 'profiles'?"),
    ("[loop]\nzzz = 1\n", "loop.zzz: unknown key 'zzz' (got 1)"),
])
def test_config_check_suggests_the_key_meant(tmp_path: Path, text: str, msg: str) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}"]\n{text}')
    p = run("config", "check", str(site))
    assert p.returncode == 2 and msg in p.stderr, p.stderr


def test_a_config_refused_names_each_of_its_errors(tmp_path: Path) -> None:
    """Each error, where and which value (the first few; the rest counted), not "[and 1 more]"."""
    from motcomp.config import MORE_ERRORS

    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}"]\n[axes.rails_x]\nvel_max_m_s = 20.0\n'
                    '[axes.rails_y]\nvel_max_m_s = 30.0\n')
    p = run("config", "check", str(site))
    assert p.returncode == 2, p.stderr
    assert "axes.rails_x.vel_max_m_s: lies outside (0, 10]" in p.stderr
    assert (f"; also {site}: axes.rails_y.vel_max_m_s: lies outside (0, 10] m/s, the plausible "
            "range of a motion platform (got 30.0)") in p.stderr, p.stderr
    many = "".join(f"[loop]\nzz{i} = {i}\n" if i == 0 else f"zz{i} = {i}\n"
                   for i in range(MORE_ERRORS + 3))
    site.write_text(f'include = ["{EXAMPLE}"]\n{many}')
    p = run("config", "check", str(site))
    assert p.returncode == 2 and p.stderr.count("; also ") == MORE_ERRORS, p.stderr
    assert p.stderr.rstrip().endswith(" [and 2 more]"), p.stderr


@pytest.mark.parametrize(("text", "msg"), [
    ("[axes.rails_y]\nvel_max_m_ss = 2.0\n",
     "axes.rails_y.vel_max_m_ss: unknown key 'vel_max_m_ss'; did you mean 'vel_max_m_s'"),
    ("[axes.rails_y]\nvel_max_m_s = 20.0\n", "axes.rails_y.vel_max_m_s: lies outside (0, 10]"),
    # 0 is outside the range the message gives, not refused by another rule after it
    ("[axes.rails_y]\nacc_max_m_s2 = 0.0\n",
     "axes.rails_y.acc_max_m_s2: lies outside (0, 100] m/s^2"),
    ("[axes.rails_z]\nbypass = true\n", "axes.rails_z: unknown axis; axes: rails_x"),
])
def test_an_error_names_the_included_file_that_holds_the_value(tmp_path: Path, text: str,
                                                                msg: str) -> None:
    """A site config of several fragments: the error names the fragment with the bad value and
    the file that includes it, not only the top file; a value of the top file names it."""
    (tmp_path / "frag").mkdir()
    (tmp_path / "frag" / "bad.toml").write_text(text)
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}", "frag/bad.toml"]\n')
    with pytest.raises(ConfigError) as err:
        load_config(site)
    assert str(err.value).startswith(f"frag/bad.toml (included by {site}): {msg}"), err.value
    site.write_text(f'include = ["{EXAMPLE}"]\n{text}')  # the same value in the top file
    with pytest.raises(ConfigError) as err:
        load_config(site)
    assert str(err.value).startswith(f"{site}: {msg}"), err.value
    site.write_text(f'include = ["{EXAMPLE}", "frag/none.toml"]\n')
    with pytest.raises(ConfigError, match=r"none\.toml: cannot read: .* \(included by .*site"):
        load_config(site)


@pytest.mark.parametrize(("text", "msg"), [
    ("[loop]\nrate_hz = true\n", "loop.rate_hz: Input should be a valid number (got true)"),
    ('[admin]\nenabled = "yes"\n', 'admin.enabled: Input should be a valid boolean (got "yes")'),
    ("[axes.rails_y.gains]\nkp = true\n",
     "axes.rails_y.gains.kp: Input should be a valid number (got true)"),
    ('[supervision]\nband_hz = ["0.1", 2.0]\n',
     'supervision.band_hz.0: Input should be a valid number (got "0.1")'),
])
def test_a_value_of_another_type_is_refused_not_coerced(tmp_path: Path, text: str,
                                                        msg: str) -> None:
    """TOML has its types: a boolean where a number goes (``true`` would read as 1), a string
    where a boolean or a number goes, is an error naming the key and the value as written."""
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}"]\n{text}')
    with pytest.raises(ConfigError) as err:
        load_config(site)
    assert msg in str(err.value), err.value


def test_integers_where_numbers_go_and_arrays_where_pairs_go_are_taken(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{EXAMPLE}"]\n[axes.rails_y]\nacc_max_m_s2 = 5\n'
                    "[supervision]\nband_hz = [1, 2]\n")
    cfg = load_config(site)
    assert cfg.axes["rails_y"].acc_max_m_s2 == 5.0
    assert cfg.supervision.band_hz == (1.0, 2.0)
