"""The identification report: the paper's Table 1 per axis, the model comparison, figures and
the config fragment the compensator reads.

:func:`report_json` is what ``motcomp identify --json`` prints; :func:`markdown` the text;
:func:`config_fragment` the TOML the service config includes::

    [axes.rails_y]
    model = "p1d:K=1.002,Td=0.01751,Tp1=0.1861"

:func:`write_report` writes everything into a directory through a temporary one, so nothing is
left half-written.  matplotlib is imported only in :func:`write_figures`.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from motcomp.core.models import ProcessModel
from motcomp.errors import ConfigError
from motcomp.ident.data import Recording
from motcomp.ident.fit import Identification, ModelFit
from motcomp.jsonsafe import finite
from motcomp.presets import input_lag_comment

__all__ = ["config_fragment", "markdown", "model_fragment", "report_json", "table1",
           "table1_markdown", "write_figures", "write_report", "write_reports"]


def _axis(ident: Identification, axis: str | None) -> str:
    return axis or ident.axis or "rails_y"


def _p1d_for_compensator(model: ProcessModel) -> str | None:
    try:
        return model.to_p1d().spec()
    except ConfigError:
        return None


def table1(ident: Identification, axis: str | None = None) -> dict[str, Any]:
    """One row of the paper's Table 1 from the selected model."""
    t = ident.best.table1
    return {
        "axis": _axis(ident, axis),
        "model": ident.selected,
        "pure_delay_ms": t["pure_delay_ms"],
        "pure_delay_ms_stderr": t["pure_delay_ms_stderr"],
        # the fit's convention: the recorded command held over each sample (zero-order hold);
        # a platform that follows a smooth command through the samples lags it half a sample more
        "pure_delay_smooth_ms": t["pure_delay_ms"] + 500.0 / ident.prep.rate_hz,
        "phase_delay_0p2hz_ms": t["phase_delay_0p2hz_ms"],
        "phase_delay_0p2hz_ms_stderr": t["phase_delay_0p2hz_ms_stderr"],
        "bandwidth_hz": t["bandwidth_hz"],
    }


def report_json(ident: Identification, axis: str | None = None) -> dict[str, Any]:
    """The ``motcomp identify --json`` object (finite numbers or null only)."""
    sel = ident.best
    t1 = table1(ident, axis)
    rec = ident.prep.recording
    out: dict[str, Any] = {
        "axis": t1["axis"],
        "source": rec.source,
        "data": {**ident.prep.summary(), **_window_json(rec)},
        "delay_search": {
            "range_ms": [ident.options.delay_min_s * 1e3, ident.options.delay_max_s * 1e3],
            "bracket_ms": [ident.bracket.lo_s * 1e3, ident.bracket.hi_s * 1e3],
            "impulse_response_peak_ms": ident.bracket.ir_peak_s * 1e3,
        },
        "models": {k: f.to_json() for k, f in ident.fits.items()},
        "failed": dict(ident.errors),
        "selected": ident.selected,
        "reason": ident.reason,
        "model_spec": sel.model.spec(),
        "compensator_p1d": _p1d_for_compensator(sel.model),
        "pure_delay_ms": t1["pure_delay_ms"],
        "pure_delay_ms_stderr": t1["pure_delay_ms_stderr"],
        "phase_delay_0p2hz_ms": t1["phase_delay_0p2hz_ms"],
        "phase_delay_0p2hz_ms_stderr": t1["phase_delay_0p2hz_ms_stderr"],
        "bandwidth_hz": t1["bandwidth_hz"],
        "table1": t1,
        "warnings": [*rec.warnings, *ident.warnings],
        "seconds": ident.seconds,
    }
    return finite(out)


def _window_json(rec: Recording) -> dict[str, Any]:
    """Where in the recording the data come from, and the gaps bridged."""
    w = rec.window
    return {"window": None if w is None else {"start_s": w.start_s, "end_s": w.end_s,
                                               "samples": w.samples, "how": w.how},
            "gaps": rec.gaps.to_json(), "conditions": dict(rec.conditions)}


def _window_text(d: dict[str, Any]) -> str:
    w, g = d["window"], d["gaps"]
    text = "" if w is None else (f"Window {w['start_s']:.2f}-{w['end_s']:.2f} s of the recording "
                                 f"({w['samples']} samples; {w['how']}). ")
    if g["count"]:
        text += (f"{g['count']} gap(s) without data bridged by linear interpolation (longest "
                 f"{g['longest_ms']:.1f} ms, {g['total_ms']:.1f} ms in all; at most "
                 f"{g['max_gap_s'] * 1e3:.0f} ms bridged).")
    else:
        text += "No gaps in the data."
    c = d.get("conditions") or {}
    if "service_missed" in c:
        text += (f"  The service missed {c['service_missed']} of "
                 f"{c['service_ticks'] + c['service_missed']} deadlines meanwhile "
                 f"({100 * c['service_missed_share']:.2f} %)")
        text += _stack_text(c.get("platform_setpoint_age_ms"), c.get("pairing_phase_ms"))
    return text


def _stack_text(age: float | None, phase: float | None) -> str:
    """The stack's share of the fitted delay: the platform's setpoint age less the pairing's
    phase, which the fit reads as the model's hold (docs/SUPERVISION.md, "The stack's
    share")."""
    if age is None:
        return "."
    text = f"; the platform applied its setpoints {age:.2f} ms after their t (median"
    if phase is None:
        return text + ": the stack's delay)."
    return (text + f"), the pairing's phase {phase:.2f} ms (the model's hold, outside the "
            f"fitted Td): {age - phase:+.2f} ms of the stack's delay inside the fitted Td.")


TREMOR_HZ = (10.0, 20.0)
"""The position controllers' holding vibration lies in this band (docs/IDENTIFICATION.md)."""


def _line_name(f_hz: float) -> str:
    """A notched line's frequency, called tremor only inside :data:`TREMOR_HZ`."""
    lo, hi = TREMOR_HZ
    return f"{f_hz:.2f} Hz" + (" (tremor)" if lo <= f_hz <= hi else "")


def _pm(value: float, se: float | None, fmt: str = ".4g") -> str:
    if se is None:
        return f"{value:{fmt}} (s.e. n/a)"
    if abs(value) > 0 and se > abs(value):
        return f"{value:{fmt}} (s.e. > 100 %)"
    return f"{value:{fmt}} ± {se:.2g}"


def _params_text(f: ModelFit, names: dict[str, float]) -> str:
    parts = []
    for k, v in names.items():
        se = f.stderr.get(k)
        scale, unit = (1e3, " ms") if k in ("Td", "Tp1", "Tp2", "Tw", "Tz") else (1.0, "")
        parts.append(f"{k} = {_pm(v * scale, se * scale if se is not None else None)}{unit}")
    return ", ".join(parts)


def _bw(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g} Hz"


def markdown(ident: Identification, axis: str | None = None) -> str:
    """A readable report: data, Table 1 row, the models compared and the choice."""
    from motcomp.ident.structures import make_structure

    rep = report_json(ident, axis)
    d = rep["data"]
    t1 = rep["table1"]
    lines = [
        f"# Identification of {rep['axis']}",
        "",
        f"Data: `{rep['source']}`, {d['samples']} samples at {d['rate_hz']:.6g} Hz "
        f"({d['duration_s']:.1f} s)" + (", resampled from irregular time stamps "
                                        f"(period jitter {d['period_jitter_ms']:.3g} ms)"
                                        if d["resampled"] else "") + ".",
        _window_text(d),
        f"Compared in the acceleration domain after a zero-phase prefilter at "
        f"{d['prefilter_cutoff_hz']:.3g} Hz (excitation band ~{d['excitation_band_hz']:.3g} Hz)"
        + (f", notches at {', '.join(_line_name(f) for f in d['notches_hz'])} (narrow lines "
           "of the measurement the command does not explain)" if d["notches_hz"] else "")
        + f"; {d['estimation_samples']} samples fitted, {d['validation_samples']} kept for "
        "validation.",
        f"Delay searched in [{rep['delay_search']['range_ms'][0]:.1f}, "
        f"{rep['delay_search']['range_ms'][1]:.1f}] ms, bracketed to "
        f"[{rep['delay_search']['bracket_ms'][0]:.1f}, {rep['delay_search']['bracket_ms'][1]:.1f}]"
        f" ms (impulse-response peak {rep['delay_search']['impulse_response_peak_ms']:.1f} ms).",
        "",
        f"## Table 1 ({rep['selected']})",
        "",
        table1_markdown([t1]),
        "",
        "## Models",
        "",
        "| model | parameters (± standard error) | fit % (val.) | VAF % (val.) | fit % raw | AIC "
        "| pure delay | phase delay 0.2 Hz | -6 dB | time |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    opts = ident.options
    for k, f in ident.fits.items():
        s = make_structure(k, opts.oe_order, opts.oe_pade)
        lines.append(
            f"| {k}{' (selected)' if k == ident.selected else ''} | "
            f"{_params_text(f, s.natural(f.model))} | {f.fit_percent:.2f} | {f.vaf_percent:.2f}"
            f" | {f.fit_percent_raw:.1f} | {f.aic:.1f} | {f.table1['pure_delay_ms']:.2f} ms | "
            f"{f.table1['phase_delay_0p2hz_ms']:.1f} ms | "
            f"{_bw(f.table1['bandwidth_hz']['-6dB'])} | {f.seconds:.2f} s |")
    for k, msg in ident.errors.items():
        lines.append(f"| {k} | failed: {msg} | | | | | | | | |")
    lines += ["", *_tradeoff_lines(ident)]
    lines += [
        f"Selected **{rep['selected']}**: {rep['reason']}.",
        "",
        *[f"**Warning**: {w}." for w in rep["warnings"]],
        *([""] if rep["warnings"] else []),
        f"Model spec: `{rep['model_spec']}`"
        + (f"; the compensator's P1D (same gain, pure delay and phase delay at 0.2 Hz): "
           f"`{rep['compensator_p1d']}`" if rep["compensator_p1d"] and
           rep["compensator_p1d"] != rep["model_spec"] else "") + ".",
        "",
    ]
    return "\n".join(lines)


DELAY_CONVENTION = (
    "Pure delay: after the recorded command held over each sample (zero-order hold, the "
    "convention of the fit and of the compensator's model); a platform that follows a smooth "
    "command through the samples lags it half a sample more (the second figure).")


def _tradeoff_lines(ident: Identification) -> list[str]:
    """One line per model with parameters the data do not tell apart (their standard errors
    above mean nothing), naming what the data do fix."""
    out = []
    for k, f in ident.fits.items():
        parts = []
        for t in f.tradeoffs:
            names = t["params"]
            if len(names) == 2:
                text = f"{names[0]} and {names[1]} (correlation {t['correlation']:+.3f})"
            else:
                text = f"{', '.join(names)} (fewer combinations of them are in the data)"
            if t.get("identified") is not None:
                text += (f": only {t['identified']} = "
                         f"{_pm(t['value_ms'], t.get('stderr_ms'), '.4g')} ms is identified")
            parts.append(text)
        if parts:
            out.append(f"**{k}: not identified separately**: {'; '.join(parts)}; the standard "
                       "errors above say nothing of each of these alone.")
    return [*out, ""] if out else []


def table1_markdown(rows: list[dict[str, Any]]) -> str:
    """The paper's Table 1, one row per axis (rows from :func:`table1`), and the delays'
    convention (:data:`DELAY_CONVENTION`)."""
    lines = ["| axis | model | pure delay (held / smooth command) | phase delay at 0.2 Hz | "
             "bandwidth (-3 dB) | bandwidth (-6 dB) |", "|---|---|---|---|---|---|"]
    for t1 in rows:
        lines.append(
            f"| {t1['axis']} | {t1['model']} | "
            f"{_pm(t1['pure_delay_ms'], t1['pure_delay_ms_stderr'], '.1f')} / "
            f"{t1['pure_delay_smooth_ms']:.1f} ms | "
            f"{_pm(t1['phase_delay_0p2hz_ms'], t1['phase_delay_0p2hz_ms_stderr'], '.1f')} ms | "
            f"{_bw(t1['bandwidth_hz']['-3dB'])} | {_bw(t1['bandwidth_hz']['-6dB'])} |")
    return "\n".join([*lines, "", DELAY_CONVENTION])


def config_fragment(ident: Identification, axis: str | None = None,
                    forced: str | None = None) -> str:
    """The TOML fragment ``[axes.<axis>] model = "<spec>"`` with the fit quality in comments;
    ``forced``: why identify refused it (written with ``--force``: :func:`model_fragment`)."""
    rep = report_json(ident, axis)
    sel = ident.best
    t1 = rep["table1"]
    d = rep["data"]
    bw3, bw6 = t1["bandwidth_hz"]["-3dB"], t1["bandwidth_hz"]["-6dB"]
    lines = [
        f"# Identified by motcomp identify from {rep['source']}",
        f"# ({d['duration_s']:.1f} s at {d['rate_hz']:.6g} Hz; prefilter "
        f"{d['prefilter_cutoff_hz']:.3g} Hz).",
        f"# Selected {rep['selected']}: validation fit {sel.fit_percent:.2f} %, "
        f"VAF {sel.vaf_percent:.2f} %, AIC {sel.aic:.1f}.",
        f"# Pure delay {t1['pure_delay_ms']:.2f} ms, phase delay at 0.2 Hz "
        f"{t1['phase_delay_0p2hz_ms']:.1f} ms, bandwidth -3 dB {_bw(bw3)}, -6 dB {_bw(bw6)}.",
    ]
    if rep["compensator_p1d"] and rep["compensator_p1d"] != rep["model_spec"]:
        lines.append(f"# The compensator reduces it to {rep['compensator_p1d']}.")
    for k, f in ident.fits.items():
        if k != ident.selected:
            lines.append(f"# Also fitted: {f.model.spec()} (validation fit "
                         f"{f.fit_percent:.2f} %, AIC {f.aic:.1f})")
    lines += input_lag_comment((d.get("conditions") or {}).get("pairing_phase_ms"))
    return model_fragment(t1["axis"], rep["model_spec"], lines, forced)


def model_fragment(axis: str, spec: str, comments: list[str], forced: str | None = None) -> str:
    """The TOML fragment ``[axes.<axis>] model = "<spec>"`` after the comment lines given.

    ``forced``: why ``motcomp identify`` refused to write it, when ``--force`` wrote it
    anyway: said in a comment and marked ``forced = { model, why }``, on which the service and
    ``motcomp config check`` warn while the axis runs that model."""
    lines = [*comments, f"[axes.{axis}]", f"model = {json.dumps(spec)}"]
    if forced is not None:
        lines[len(comments):len(comments)] = [f"# FORCED (--force) although: {forced}"]
        lines.append(f"forced = {{ model = {json.dumps(spec)}, why = {json.dumps(forced)} }}")
    return "\n".join([*lines, ""])


def write_figures(ident: Identification, out_dir: Path) -> list[Path]:
    """``identification.png`` (signals, prediction vs measurement, spectra: the paper's Fig. 1),
    ``bode.png`` (fitted models and the data's own frequency response) and
    ``delay_profile.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import signal

    prep = ident.prep
    rec = prep.recording
    rate = prep.rate_hz
    t = rec.t
    sel = ident.best
    colors = {"p1d": "C1", "p2d": "C2", "p2uzd": "C3", "oe": "C4"}
    written = []

    # 1. signals, prediction vs measurement, spectra
    fig, axes = plt.subplots(3, 1, figsize=(10, 10))
    ax = axes[0]
    ax.plot(t, rec.cmd, color="C0", lw=0.8)
    ax.set_ylabel("command (axis units)", color="C0")
    ax2 = ax.twinx()
    ax2.plot(t, rec.acc - sel.bias, color="0.5", lw=0.4, alpha=0.7)
    ax2.set_ylabel("measured acceleration, bias removed (axis units/s^2)", color="0.4")
    ax.set_title(f"{_axis(ident, None)}: identification signals")
    ax.set_xlabel("time (s)")
    # a validation block for the zoom
    val_idx = np.nonzero(prep.val)[0]
    centre = int(val_idx[val_idx.size // 2]) if val_idx.size else t.size // 2
    half = int(min(2.5 * rate, t.size // 4))
    sl = slice(max(centre - half, 0), min(centre + half, t.size))
    ax = axes[1]
    ax.plot(t[sl], prep.y[sl], color="k", lw=1.2, label="measured (prefiltered)")
    for k, f in ident.fits.items():
        ax.plot(t[sl], f.prediction[sl], color=colors.get(k), lw=0.9,
                label=f"{k}: fit {f.fit_percent:.1f} %")
    ax.set_title("model prediction vs measurement (validation data)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("acceleration (axis units/s^2)")
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[2]
    nper = min(t.size, int(8 * rate))
    offset = sel.bias - prep.acc_mean  # the fitted bias in the mean-removed signal
    f_m, p_m = signal.welch(prep.y_raw - offset, fs=rate, nperseg=nper)
    f_p, p_p = signal.welch(sel.prediction_raw - offset, fs=rate, nperseg=nper)
    f_r, p_r = signal.welch(prep.y_raw - sel.prediction_raw, fs=rate, nperseg=nper)
    top = min(rate / 2, 4 * prep.cutoff_hz)
    for fx, px, lab, c in ((f_m, p_m, "measured", "k"), (f_p, p_p, f"{ident.selected} model",
                                                         colors.get(ident.selected, "C1")),
                           (f_r, p_r, "residual", "0.6")):
        keep = (fx > 0) & (fx <= top)
        ax.semilogy(fx[keep], px[keep], color=c, lw=1.0, label=lab)
    for f0 in prep.notches_hz:
        ax.axvline(f0, color="C3", ls=":", lw=0.8)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("acceleration PSD ((axis units/s^2)^2/Hz)")
    ax.set_title("acceleration spectra" + (" (dotted: tremor lines notched)"
                                           if prep.notches_hz else ""))
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out_dir / "identification.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    # 2. Bode plot: fitted models and the empirical frequency response (H1, coherent bins)
    f_grid = np.geomspace(0.05, max(2 * prep.cutoff_hz, 1.0), 400)
    nper = min(prep.v.size, int(10 * rate))
    fe, pvy = signal.csd(prep.v_raw, prep.y_raw, fs=rate, nperseg=nper)
    _, pvv = signal.welch(prep.v_raw, fs=rate, nperseg=nper)
    _, coh = signal.coherence(prep.v_raw, prep.y_raw, fs=rate, nperseg=nper)
    ok = (fe > 0) & (coh > 0.8) & (fe <= prep.cutoff_hz)
    h1 = pvy[ok] / pvv[ok]
    fe = fe[ok]
    fig, (axm, axp) = plt.subplots(2, 1, figsize=(9, 8), sharex=True)
    # remove the zero-order hold's half-sample lag so the data compare with continuous models
    h1 = h1 * np.exp(1j * np.pi * fe / rate)
    axm.semilogx(fe, 20 * np.log10(np.abs(h1)), ".", color="0.5", ms=3,
                 label="data (H1, coherence > 0.8)")
    with np.errstate(divide="ignore", invalid="ignore"):
        ph = np.unwrap(np.angle(h1))
        axp.semilogx(fe, -ph / (2 * np.pi * fe) * 1e3, ".", color="0.5", ms=3)
    for k, f in ident.fits.items():
        m = f.model
        axm.semilogx(f_grid, 20 * np.log10(m.magnitude(f_grid)), color=colors.get(k),
                     label=k, lw=1.4 if k == ident.selected else 0.9)
        axp.semilogx(f_grid, m.phase_delay(f_grid) * 1e3, color=colors.get(k),
                     lw=1.4 if k == ident.selected else 0.9)
    axm.axhline(-3, color="0.7", ls=":", lw=0.8)
    axm.axhline(-6, color="0.7", ls=":", lw=0.8)
    axp.axvline(0.2, color="0.7", ls=":", lw=0.8)
    axm.set_ylabel("gain (dB)")
    axp.set_ylabel("phase delay (ms)")
    axp.set_xlabel("frequency (Hz)")
    axm.set_title(f"{_axis(ident, None)}: fitted models (command -> motion)")
    axm.legend(fontsize=8)
    ylo = min(0.0, float(np.nanmin(sel.model.phase_delay(f_grid) * 1e3))) - 10
    yhi = float(np.nanmax(sel.model.phase_delay(f_grid) * 1e3)) * 1.5 + 10
    axp.set_ylim(ylo, yhi)
    fig.tight_layout()
    path = out_dir / "bode.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    # 3. delay profiles
    fig, axes2 = plt.subplots(1, 2, figsize=(11, 4))
    for k, f in ident.fits.items():
        tc, pc = f.profile_coarse
        tf, pf = f.profile_fine
        axes2[0].plot(tc * 1e3, pc / np.nanmin(pc), color=colors.get(k), lw=1, label=k)
        if tf.size:
            axes2[1].plot(tf * 1e3, pf / np.nanmin(pf), "o-", color=colors.get(k), ms=3,
                          lw=0.8, label=k)
        axes2[1].axvline(f.model.pure_delay_s * 1e3, color=colors.get(k), ls=":", lw=0.8)
    axes2[0].set_yscale("log")
    axes2[0].set_title("coarse profile (decimated data)")
    axes2[1].set_title("fine profile (full rate), dotted: final delay")
    for a in axes2:
        a.set_xlabel("delay (ms)")
        a.set_ylabel("error / its minimum")
        a.legend(fontsize=8)
    fig.tight_layout()
    path = out_dir / "delay_profile.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


def _write_one(ident: Identification, directory: Path, axis: str | None, figures: bool,
               fragment: bool = True, forced: str | None = None) -> list[Path]:
    name = _axis(ident, axis)
    (directory / "report.json").write_text(
        json.dumps(report_json(ident, axis), indent=2, allow_nan=False) + "\n")
    (directory / "report.md").write_text(markdown(ident, axis))
    files = [directory / "report.json", directory / "report.md"]
    if fragment:
        (directory / f"{name}.toml").write_text(config_fragment(ident, axis, forced))
        files.append(directory / f"{name}.toml")
    if figures:
        files += write_figures(ident, directory)
    return files


def _commit(tmp_path: Path, out_dir: Path) -> list[Path]:
    """Move everything from ``tmp_path`` into ``out_dir`` (after it has all been written)."""
    final = []
    for p in sorted(tmp_path.rglob("*")):
        if p.is_file():
            target = out_dir / p.relative_to(tmp_path)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(p), target)
            final.append(target)
    return final


def write_report(ident: Identification, out_dir: Path, axis: str | None = None,
                 figures: bool = True, fragment: bool = True,
                 forced: str | None = None) -> list[Path]:
    """Write ``report.json``, ``report.md``, ``<axis>.toml`` (unless not ``fragment``; marked
    ``forced``: :func:`model_fragment`) and (optionally) the figures into ``out_dir``, through a
    temporary directory: on any failure nothing is left behind."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out_dir, prefix=".tmp-") as tmp:
        _write_one(ident, Path(tmp), axis, figures, fragment, forced)
        return _commit(Path(tmp), out_dir)


def write_reports(idents: dict[str, Identification], out_dir: Path, figures: bool = True,
                  no_fragment: frozenset[str] = frozenset(),
                  forced: dict[str, str] | None = None) -> list[Path]:
    """Several axes of one recording: a sub-directory per axis with its full report, and at the
    top ``table1.md`` / ``table1.json`` (one row per axis) and ``axes.toml`` (the fragment of
    every axis not in ``no_fragment``; those in ``forced`` marked so), all written before any
    is moved into place."""
    forced = forced or {}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [table1(ident, axis) for axis, ident in idents.items()]
    with tempfile.TemporaryDirectory(dir=out_dir, prefix=".tmp-") as tmp:
        tmp_path = Path(tmp)
        for axis, ident in idents.items():
            (tmp_path / axis).mkdir()
            _write_one(ident, tmp_path / axis, axis, figures, axis not in no_fragment,
                       forced.get(axis))
        (tmp_path / "table1.md").write_text(table1_markdown(rows) + "\n")
        (tmp_path / "table1.json").write_text(
            json.dumps(finite(rows), indent=2, allow_nan=False) + "\n")
        (tmp_path / "axes.toml").write_text(
            "\n".join(config_fragment(ident, axis, forced.get(axis))
                      for axis, ident in idents.items() if axis not in no_fragment))
        return _commit(tmp_path, out_dir)
