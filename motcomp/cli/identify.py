"""``motcomp identify DATA``: fit P1D, P2D, P2UZD and OE models to a recorded axis."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from motcomp.cli._common import positive_float, print_json, rate_arg
from motcomp.core.axes import AXIS_INDEX
from motcomp.errors import ConfigError, DataError, MotcompError
from motcomp.ident.data import DEFAULT_MAX_GAP_S
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args

if TYPE_CHECKING:
    from motcomp.ident.fit import Identification

MIN_FIT_PERCENT = 50.0
"""A fit whose validation fit is below this (the model explains less than half the measured
acceleration's deviation) is not written as a config fragment without ``--force``."""
MAX_MISSED_SHARE_FRAGMENT = 0.05
"""Nor is one from a run in which the service missed more than this share of its deadlines (a
host that cannot hold the loop rate; the report warns from 2 %:
:data:`motcomp.runtime.clock.DEGRADED_MISSED_SHARE`)."""
ORDER = 5


def _models(text: str) -> tuple[str, ...]:
    kinds = tuple(k.strip().lower() for k in text.split(",") if k.strip())
    if not kinds:
        raise argparse.ArgumentTypeError("give at least one model, e.g. p1d,p2d")
    return kinds


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "identify", help="identify an axis' delay and dynamics from a recording",
        description="Fit P1D, P2D, P2UZD and OE models (delay included) to a recording of the "
                    "command and the measured acceleration; print the paper's Table 1 row and "
                    "the model comparison; write report.json, report.md, figures and the config "
                    "fragment <axis>.toml into --out.  From an MCAP recording of the stack, the "
                    "command is the service's output in force at each feedback sample (what "
                    "the platform received, platform/setpoint) and the measurement the "
                    "feedback's acceleration, on the longest stretch where the axis is bypassed "
                    "and not limited (or --window).")
    p.add_argument("data", type=Path, metavar="DATA", nargs="?",
                   help="CSV with columns t,cmd,acc (s, m or rad, m/s^2 or rad/s^2) or an MCAP "
                        "session recording (motcomp record); with --live, the recording to "
                        "write (MCAP); with --from-status, a status saved by 'motcomp status "
                        "--json' (default: ask the running service)")
    sup = p.add_argument_group(
        "the model supervision's estimate as a fragment (--from-status; docs/SUPERVISION.md)")
    sup.add_argument("--from-status", action="store_true",
                     help="write the running service's current estimate of --axis (its "
                          "status' model_mismatch block; default: the axis in alarm) as the "
                          "config fragment <axis>.toml into --out; exit 2 without a fragment "
                          "when the estimate is not informative or describes no plausible "
                          "platform (--force writes it, marked forced)")
    sup.add_argument("--status-key", default="motcomp/status", metavar="KEY",
                     help="the service's status key (default: motcomp/status)")
    live = p.add_argument_group(
        "identification run through the running stack (--live; docs/IDENTIFICATION.md)")
    live.add_argument("--live", action="store_true",
                      help="bypass --axis on the running service (its admin endpoints must be "
                           "enabled; no other motion source may publish), play an excitation "
                           "on its input, record to DATA, restore the axis' mode, identify")
    live.add_argument("--excite", choices=("multisine", "noise", "sweep"), default="multisine",
                      help="excitation kind (default: multisine)")
    live.add_argument("--excite-s", type=positive_float, default=40.0, metavar="S",
                      help="excitation length, fades and holds included (default: 40)")
    live.add_argument("--usage", type=positive_float, default=0.5, metavar="FRACTION",
                      help="fraction of the axis' tightest limit the excitation reaches "
                           "(default: 0.5, which the service's limiter leaves alone)")
    live.add_argument("--admin-key", default="motcomp/admin", metavar="KEY",
                      help="the service's admin key (default: motcomp/admin)")
    add_zenoh_args(p)
    p.add_argument("--axis", metavar="NAME",
                   help="axis name (default: from the data, else rails_y); for a recording of "
                        "several axes, a comma-separated list or 'all' (every axis whose "
                        "command moves; those without usable data, or whose fit fails, are left "
                        "out with a warning)")
    p.add_argument("--models", type=_models, default=("p1d", "p2d", "p2uzd", "oe"),
                   metavar="LIST", help="models to fit (default: p1d,p2d,p2uzd,oe)")
    p.add_argument("--delay-range", nargs=2, type=float, default=(0.0, 250.0),
                   metavar=("MIN_MS", "MAX_MS"), help="pure delay searched (default: 0 250)")
    p.add_argument("--oe-order", type=int, default=2, metavar="N",
                   help="order of the OE model's rational part (default: 2)")
    p.add_argument("--oe-pade", type=int, default=1, metavar="N",
                   help="Pade order of the OE model's delay, 0 for an exact delay (default: 1)")
    p.add_argument("--cutoff", type=rate_arg, default=None, metavar="HZ",
                   help="prefilter cut-off (default: from the command's spectrum)")
    p.add_argument("--no-notch", action="store_true",
                   help="do not notch narrow lines of the measurement (tremor)")
    p.add_argument("--select-tolerance", type=float, default=1.0, metavar="POINTS",
                   help="validation fit %% points a simpler model may trail by (default: 1)")
    p.add_argument("--rate", type=rate_arg, default=None, metavar="HZ",
                   help="resampling rate for irregular time stamps (default: the mean rate)")
    p.set_defaults(within=None)  # --live: the excitation's bounds
    p.add_argument("--window", nargs=2, type=float, default=None, metavar=("START", "END"),
                   help="identify this stretch, in seconds from the recording's start (default: "
                        "an MCAP recording's longest stretch, of 5 s or more, with the axis "
                        "bypassed and not limited, else the whole data); compensation or "
                        "limiting inside it is warned about")
    p.add_argument("--max-gap", type=float, default=DEFAULT_MAX_GAP_S, metavar="SECONDS",
                   help="bridge gaps in the data up to this long by linear interpolation "
                        "(counted in the report); a longer gap ends the automatic window, or "
                        f"is an error inside --window or a CSV (default: {DEFAULT_MAX_GAP_S:g})")
    p.add_argument("--clock", choices=("frame", "log"), default="frame",
                   help="MCAP time stamps used to find the output in force at each feedback "
                        "sample: 'frame' (default), the frames' own t (the service's tick "
                        "time, the platform's measurement time): right when the service and "
                        "the platform share a clock (one host, or PTP/NTP); 'log', the "
                        "recorder's receive times, only when those clocks are not synchronised: "
                        "the recorder's delivery then shifts and blurs the pairing.  The command "
                        "is always the output in force, never the service's input")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output directory (default: DATA without suffix + '_ident')")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--force", action="store_true",
                   help=f"write the config fragment even when the fit explains little of the "
                        f"measurement (validation fit below {MIN_FIT_PERCENT:g} %%) or the "
                        "service missed more than 5 %% of its deadlines (exit 2 without it), "
                        "marked forced (config check and the service warn); with --live, run "
                        "even when the service misses them before the run")
    p.set_defaults(func=run_identify)


def _axes(args: argparse.Namespace) -> list[str | None]:
    """``--axis``: one name, a comma-separated list, ``all`` (every axis the recording moves),
    or nothing (the data's own axis)."""
    from motcomp.ident.data import list_axes

    if args.axis is None:
        return [None]
    if args.axis == "all":
        found = list_axes(args.data, args.clock)
        return list(found) if found else [None]
    names = [a.strip() for a in args.axis.split(",") if a.strip()]
    for a in names:
        if a not in AXIS_INDEX:
            raise ConfigError(f"--axis: unknown axis {a!r}; axes are {', '.join(AXIS_INDEX)}")
    if len(set(names)) != len(names):
        raise ConfigError(f"--axis: {args.axis!r} names an axis twice")
    return list(names)


def run_identify(args: argparse.Namespace) -> int:
    from motcomp.ident.data import load_recording
    from motcomp.ident.fit import FitOptions, identify
    from motcomp.ident.report import (
        markdown,
        report_json,
        table1,
        table1_markdown,
        write_report,
        write_reports,
    )
    from motcomp.progress import Progress

    if args.from_status:
        if args.live:
            raise ConfigError("--from-status and --live exclude each other")
        return _run_from_status(args)
    if args.data is None:
        raise ConfigError("identify needs DATA (a recording), or --from-status")
    if args.live:
        _run_live(args)
    axes = _axes(args)
    lo_ms, hi_ms = args.delay_range
    options = FitOptions(models=args.models, delay_min_s=lo_ms * 1e-3, delay_max_s=hi_ms * 1e-3,
                         oe_order=args.oe_order, oe_pade=args.oe_pade, cutoff_hz=args.cutoff,
                         notch=not args.no_notch, select_tolerance=args.select_tolerance)
    idents: dict[str, Identification] = {}
    data_warnings: list[str] = []  # the reader's, once; the windows', per axis
    refused: list[str] = []
    stages = len(axes) * (1 + 4 * len(options.models))
    # every axis is identified before anything is written
    try:
        with _reader_log_muted(), \
                Progress("identify", total=stages, quiet=args.quiet) as bar:
            for name in axes:
                try:
                    rec = load_recording(args.data, axis=name, rate_hz=args.rate,
                                         clock=args.clock, window=args.window,
                                         max_gap_s=args.max_gap,
                                         within=args.within)
                except DataError as exc:
                    if args.axis != "all" or len(axes) == 1:
                        raise
                    # 'all': an axis without usable data is left out, with the reason
                    refused.append(str(exc))
                    bar.advance(1 + 4 * len(options.models), note=f"{name}: left out")
                    continue
                axis = name or rec.axis or "rails_y"
                prefix = f"{axis}: " if len(axes) > 1 else ""
                data_warnings += rec.warnings  # the file's, and the window's naming the axis

                def note(msg: str, prefix: str = prefix) -> None:
                    bar.advance(note=prefix + msg)
                try:
                    idents[axis] = identify(rec, options, progress=note)
                except MotcompError as exc:
                    if args.axis != "all" or len(axes) == 1:
                        raise
                    refused.append(f"{args.data}: {axis}: {exc}")  # 'all': left out too
    except MotcompError:
        _print_warnings(data_warnings)
        raise
    if not idents:
        raise DataError(f"no axis of {args.data} can be identified: {'; '.join(refused)}")
    data_warnings += [f"left out: {msg}" for msg in refused]
    out = args.out or args.data.with_name(args.data.stem + "_ident")
    poor = {axis: _untrusted(ident) for axis, ident in idents.items()}
    poor = {axis: why for axis, why in poor.items() if why}
    held = frozenset(poor) if not args.force else frozenset()
    forced = poor if args.force else {}
    if not args.quiet:  # the figures take seconds of their own on a slow host
        print(f"identify: writing the report{'' if args.no_figures else ' and figures'} to "
              f"{out}", file=sys.stderr)
    try:
        if len(idents) == 1:
            (axis, ident), = idents.items()
            written = write_report(ident, out, axis=axis, figures=not args.no_figures,
                                   fragment=axis not in held, forced=forced.get(axis))
        else:
            written = write_reports(idents, out, figures=not args.no_figures, no_fragment=held,
                                    forced=forced)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot write the report: {exc.strerror or exc}"
                          ) from None
    if len(idents) == 1:
        (axis, ident), = idents.items()
        obj = report_json(ident, axis)
        text = markdown(ident, axis)
    else:
        obj = {"axes": {a: report_json(i, a) for a, i in idents.items()},
               "table1": [table1(i, a) for a, i in idents.items()]}
        text = "\n".join(["# Table 1", "", table1_markdown(obj["table1"]), "",
                          *(markdown(i, a) for a, i in idents.items())])
    if args.json:
        obj["files"] = [str(p) for p in written]
        print_json(obj)
    else:
        sys.stdout.write(text)
        print(f"wrote {', '.join(str(p) for p in written)}")
    _print_warnings(data_warnings)
    for axis, ident in idents.items():
        where = f"{axis}: " if len(idents) > 1 else ""
        for kind, msg in ident.errors.items():
            print(f"warning: {where}{kind} could not be fitted: {msg}", file=sys.stderr)
        for msg in ident.warnings:
            print(f"warning: {where}{msg}", file=sys.stderr)
    for axis, why in poor.items():
        print(f"{'warning' if args.force else 'error'}: {axis}: {why}; "
              + ("its config fragment is written anyway (--force), marked forced: `motcomp "
                 "config check` and the service warn while it is the axis' model"
                 if args.force else
                 f"no config fragment written (the report in {out} says more; --force writes "
                 "it anyway)"), file=sys.stderr)
    return 2 if held else 0


def _run_from_status(args: argparse.Namespace) -> int:
    """``--from-status``: the status' estimate of one axis as a config fragment."""
    import json
    import time

    from motcomp.ident.report import model_fragment
    from motcomp.presets import input_lag_comment

    if args.data is not None:
        try:
            st = json.loads(args.data.read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{args.data}: not a status saved as JSON: {exc}") from None
        where = str(args.data)
    else:
        from motcomp.cli.admin import _ask
        from motcomp.io.zenoh_io import open_session

        ep = endpoints_from_args(args)
        with open_session(ep) as session:
            st = _ask(session, ep, args.status_key, None, 3.0)
        where = f"the service at {ep.describe()}"
    block = st.get("model_mismatch") if isinstance(st, dict) else None
    if not isinstance(block, dict) or not isinstance(block.get("axes"), dict):
        raise DataError(f"{where}: the status has no model_mismatch block (a service without "
                        "supervision, or an older version)")
    axes = block["axes"]
    axis = args.axis
    if axis is None:
        alarmed = [a for a, f in axes.items() if isinstance(f, dict) and f.get("alarm")]
        if len(alarmed) != 1:
            how = "none is" if not alarmed else "several are"
            states = ", ".join(f"{a} ({f.get('state') or 'state unknown'})" if isinstance(f, dict)
                               else a for a, f in axes.items())
            raise ConfigError(f"--axis: give the axis ({how} in alarm; the axes supervision "
                              f"watches, with their state: {states or 'none'})")
        axis = alarmed[0]
    fig = axes.get(axis)
    if not isinstance(fig, dict):
        raise DataError(f"{where}: {axis} is not supervised (the axes supervision watches: "
                        f"{', '.join(axes) or 'none'})")
    taken = "the latest window"
    stale_note = None
    earlier = fig.get("last_informative")
    if isinstance(earlier, dict) and not (fig.get("informative")
                                          and isinstance(fig.get("estimate"), dict)):
        # the latest window told nothing (stalls, no motion): the last one that did
        taken = (f"the last informative window (the latest is not: "
                 f"{fig.get('reason') or 'no estimate'})")
        now_t, end_t = st.get("t"), earlier.get("to_t")
        if isinstance(now_t, int | float) and isinstance(end_t, int | float):
            age = float(now_t) - float(end_t)
            stale_note = (f"{axis}: the estimate is from a window that ended {age:.0f} s before "
                          f"the status; the axis is {fig.get('state') or 'not judged'} now"
                          + (f" (no window judged for {float(fig['blind_s']):.0f} s)"
                             if isinstance(fig.get("blind_s"), int | float) else "")
                          + ": the platform may have changed since")
        fig = earlier
    est = fig.get("estimate")
    if not isinstance(est, dict):
        raise DataError(f"{where}: {axis}: no estimate yet ({fig.get('reason') or 'waiting'})")
    informative = bool(fig.get("informative"))
    end = fig.get("to_t")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(
        float(end) if isinstance(end, int | float) else float(st.get("t", 0.0))))
    comments = [
        f"# Estimated by motcomp's model supervision from ordinary driving ({where}),",
        f"# {taken}, ending {when}:",
        f"# {fig['to_t'] - fig['from_t']:.0f} s window, judged at {fig['at_hz']:.2f} Hz; "
        f"identified {est['identified']}; the model explains {100 * est['explained']:.2f} %.",
        f"# Td {est['Td_ms']:.2f} +- {est['Td_se_ms']:.2f} ms, "
        + ("" if est.get("Tp1_ms") is None else
           f"Tp1 {est['Tp1_ms']:.1f} +- {est['Tp1_se_ms']:.1f} ms, ")
        + f"K {est['K']:.4f} +- {est['K_se']:.4f}.",
        f"# Against the model then in force ({fig['model']}): residual delay "
        f"{fig['residual_delay_ms']:+.2f} +- {fig['residual_delay_se_ms']:.2f} ms, gain error "
        f"{100 * fig['gain_error']:+.2f} % in the band.",
        *input_lag_comment(fig.get("pairing_phase_ms")),
        *([f"# Note: {stale_note}."] if stale_note else []),
    ]
    out = args.out or Path(f"retune_{axis}")
    refusals = ([] if informative else [f"not informative ({fig.get('reason')})"]) + [
        f"implausible: {why}" for why in implausible(est, fig)]
    if refusals and not args.force:
        print(f"error: {axis}: the estimate is {'; '.join(refusals)}; no config fragment "
              "written (--force writes it anyway, marked forced)", file=sys.stderr)
        return 2
    forced = "; ".join(refusals) if refusals else None
    try:
        out.mkdir(parents=True, exist_ok=True)
        path = out / f"{axis}.toml"
        path.write_text(model_fragment(axis, est["spec"], comments, forced))
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot write the fragment: {exc.strerror or exc}"
                          ) from None
    if args.json:
        print_json({"axis": axis, "fragment": str(path), "spec": est["spec"], **fig,
                    "taken": taken})
    else:
        print("\n".join(comments))
        print(f"wrote {path}")
    if stale_note:
        print(f"warning: {stale_note}", file=sys.stderr)
    return 0


PLAUSIBLE_GAIN = (0.5, 2.0)
"""An estimate's gain within these multiples of the model's: a platform moves about what it is
told, and an accelerometer's scale does not change in service."""
PLAUSIBLE_SE = {"Td": 10.0, "Tp1": 0.25, "K": 0.1}
"""Largest standard errors of a plausible estimate: ``Td`` in ms, ``Tp1`` and ``K`` relative."""
ESTIMATE_BOUNDS_MS = {"Td": (0.0, 250.0), "Tp1": (0.1, 2000.0)}
"""The supervision fit's bounds (motcomp.runtime.estimate): an estimate on one is the search's
end, not a platform."""


def implausible(est: dict[str, Any], fig: dict[str, Any]) -> list[str]:
    """Why the supervision's estimate ``est`` (of the status block ``fig``) describes no
    plausible platform: a parameter on the fit's bounds or undetermined, a gain far from the
    model's, a model that explains too little.  Empty when plausible."""
    from motcomp.core.models import parse_model

    why = []
    for name, (lo, hi) in ESTIMATE_BOUNDS_MS.items():
        v = est.get(f"{name}_ms")
        if isinstance(v, int | float) and not lo + 1e-3 < v < hi - 1e-3:
            why.append(f"{name} {v:.2f} ms is on the fit's bound ({lo:g}-{hi:g} ms)")
    td_se, tp_se, tp = est.get("Td_se_ms"), est.get("Tp1_se_ms"), est.get("Tp1_ms")
    if not (isinstance(td_se, int | float) and td_se <= PLAUSIBLE_SE["Td"]):
        why.append(f"Td is undetermined (+-{td_se} ms, more than {PLAUSIBLE_SE['Td']:g} ms)")
    if isinstance(tp, int | float) and not (isinstance(tp_se, int | float)
                                            and tp_se <= PLAUSIBLE_SE["Tp1"] * tp):
        why.append(f"Tp1 is undetermined ({tp:.1f} +- {tp_se} ms)")
    k, k_se = est.get("K"), est.get("K_se")
    try:
        k_model = parse_model(str(fig.get("model"))).gain
    except (ConfigError, ValueError):
        k_model = 1.0
    if not isinstance(k, int | float) or not (
            PLAUSIBLE_GAIN[0] <= k / k_model <= PLAUSIBLE_GAIN[1]):
        why.append(f"its gain K = {k} is not within {PLAUSIBLE_GAIN[0]:g}-"
                   f"{PLAUSIBLE_GAIN[1]:g} times the model's ({k_model:g})")
    elif not (isinstance(k_se, int | float) and k_se <= PLAUSIBLE_SE["K"] * abs(k)):
        why.append(f"K is undetermined ({k:.3f} +- {k_se})")
    explained = est.get("explained")
    if not (isinstance(explained, int | float) and explained >= 0.5):
        why.append(f"it explains {explained} of the measured acceleration (less than half)")
    return why


def _untrusted(ident: Identification) -> str:
    """Why the identification must not become a config fragment without ``--force`` ("" if
    it may): a fit that explains too little, or a run the host starved."""
    fit = ident.best.fit_percent
    if not fit >= MIN_FIT_PERCENT:
        return (f"the selected {ident.selected}'s validation fit is {fit:.1f} %, below "
                f"{MIN_FIT_PERCENT:g} %: the model does not explain the measurement (check the "
                "window, the prefilter --cutoff and the excitation)")
    share = ident.prep.recording.conditions.get("service_missed_share")
    if share is not None and share > MAX_MISSED_SHARE_FRAGMENT:
        return (f"the service missed {100 * share:.1f} % of its deadlines while the data were "
                f"recorded (more than {100 * MAX_MISSED_SHARE_FRAGMENT:g} %): the fit carries "
                "the host's stalls; identify again on a quiet host")
    return ""


def _run_live(args: argparse.Namespace) -> None:
    """``--live``: the identification run (:mod:`motcomp.ident.live`); then ``args`` points at
    the recording, which says where the excitation lies (the automatic window is searched
    there: a sender's stall leaves the input stale and the limiter acting for a while, and the
    window is the longest stretch without that), and says whether the limiter acted in the
    excitation."""
    from motcomp.ident.live import LiveOptions, run_live
    from motcomp.record.session import read_session

    if args.axis is None or args.axis not in AXIS_INDEX:
        raise ConfigError("--live needs --axis NAME (one axis)")
    if args.window is not None:
        raise ConfigError("--live chooses the window itself (the excitation's): drop --window")
    if not args.data.parent.is_dir():  # before the axis is bypassed and excited
        raise ConfigError(f"{args.data}: directory {args.data.parent} does not exist (create it "
                          "first)")
    run = run_live(LiveOptions(axis=args.axis, out=args.data, kind=args.excite,
                               duration_s=args.excite_s, usage=args.usage,
                               admin_key=args.admin_key, quiet=args.quiet,
                               max_missed_share=None if args.force
                               else MAX_MISSED_SHARE_FRAGMENT),
                   endpoints_from_args(args))
    cols = read_session(run.path).identification_columns(args.axis, "frame")
    t0, t1 = (t - cols.start_s for t in run.window_unix_s)
    inside = (cols.t - cols.start_s >= t0) & (cols.t - cols.start_s <= t1)
    limited = int(cols.limited[inside].sum())
    compensated = int((~cols.bypassed[inside]).sum())
    skipped = (f"; {run.frames_skipped} samples not sent: their instants passed while the "
               "sender was stalled (a busy host)" if run.frames_skipped else "")
    print(f"live: {run.frames_sent} excitation frames on {args.axis} "
          f"({run.excitation['kind']}, {args.usage:g} of its limits) recorded to {run.path}"
          f"{skipped}; "
          f"excitation {t0:.2f}-{t1:.2f} s; limiter acted on {limited} of {int(inside.sum())} "
          f"feedback samples, compensation on at {compensated}; axis "
          f"{'left bypassed' if run.was_bypassed else 'compensated again'}", file=sys.stderr)
    # the window (the excitation's, written into the recording) and the prefilter (from the
    # reference's band) are the recording's own: `identify FILE` on it gives the same answer


def _print_warnings(warnings: list[str]) -> None:
    for msg in dict.fromkeys(warnings):
        print(f"warning: {msg}", file=sys.stderr)


@contextlib.contextmanager
def _reader_log_muted() -> Iterator[None]:
    """The recording reader logs a file cut short; identify prints that warning itself, once,
    with the others."""
    log = logging.getLogger("motcomp.record")
    null, propagate = logging.NullHandler(), log.propagate
    log.addHandler(null)
    log.propagate = False
    try:
        yield
    finally:
        log.removeHandler(null)
        log.propagate = propagate
