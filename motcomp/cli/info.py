"""``motcomp info FILE.mcap``: what a recording holds, without replaying it.

Duration, the keys with their message counts, rates and gaps, the recorded config's hash, and
the mode switches the service's output flags show (bypass per axis on/off, stale, rejoin and
parking episodes, saturated outputs per axis); a warning if the file is unfinished.  Times are
seconds from the first message of the recording (the recorder's receive times).  A key's rate
and gaps are taken on its frames' own ``t`` where they carry one (the input's, the outputs',
the feedback's): a recorder its host stalled receives the frames late and in a burst, which is
not a gap in what was sent nor a faster rate.  How long the recorder itself received nothing is
shown apart (``recorder_stall``).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from motcomp.cli._common import positive_float, print_json
from motcomp.core.axes import AXES

ORDER = 7

MIN_GAP_S = 0.02
GAP_PERIODS = 5
"""A gap is an interval between two messages of a key longer than ``GAP_PERIODS`` times the
key's median interval (and at least ``MIN_GAP_S``), unless ``--gap-s`` says otherwise."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info", help="summarise a recording (keys, rates, gaps, mode switches)",
        description="Summarise a recording without replaying it: duration, keys with message "
                    "counts and rates, gaps per key, the config hash, and the mode switches seen "
                    "in the service's output flags (bypass per axis, stale/rejoin/parking "
                    "episodes, saturation).  Times are seconds from the recording's first "
                    "message.")
    p.add_argument("files", type=Path, nargs="+", metavar="FILE.mcap",
                   help="a recording (or the name of a rotated one: FILE-0001.mcap...)")
    p.add_argument("--gap-s", type=positive_float, default=None, metavar="S",
                   help=f"count intervals longer than S seconds as gaps (default: "
                        f"{GAP_PERIODS} times the key's median interval, at least "
                        f"{MIN_GAP_S:g} s)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    summaries = [summarise(f, args.gap_s) for f in args.files]
    if args.json:
        print_json(summaries if len(summaries) > 1 else summaries[0])
    else:
        print("\n\n".join(format_info(s) for s in summaries))
    return 0


def _gaps(t_s: np.ndarray, at_s: np.ndarray, gap_s: float | None) -> dict[str, Any]:
    """Gaps between the instants ``t_s`` (sorted), each placed on the recording's timeline at
    ``at_s`` of the message before it."""
    if t_s.size < 2:
        return {"count": 0, "longest_s": 0.0, "longest_at_s": None, "threshold_s": gap_s}
    d = np.diff(t_s)
    limit = gap_s if gap_s is not None else max(MIN_GAP_S, GAP_PERIODS * float(np.median(d)))
    big = np.flatnonzero(d > limit)
    if not big.size:
        return {"count": 0, "longest_s": 0.0, "longest_at_s": None, "threshold_s": limit}
    k = int(big[np.argmax(d[big])])
    return {"count": int(big.size), "longest_s": float(d[k]), "longest_at_s": float(at_s[k]),
            "threshold_s": limit}


def _lost(seq: np.ndarray) -> int:
    """Frames missing from a key whose ``seq`` counts the frames sent (in the order received):
    the numbers skipped by each step forward of at most ``MAX_SEQ_STEP`` (a larger step, or one
    back, is another sender or a restarted one: docs/WIRE.md)."""
    from motcomp.core.tick import MAX_SEQ_STEP

    d = np.diff(seq.astype(np.int64))
    skip = d[(d > 1) & (d <= MAX_SEQ_STEP)]
    return int(np.sum(skip - 1))


RATE_SPAN = 10
"""A key's rate is taken over spans of this many intervals (:func:`_rate_hz`)."""


def _rate_hz(inst: np.ndarray) -> float:
    """``RATE_SPAN`` over the median time of ``RATE_SPAN`` consecutive intervals of the sorted
    instants ``inst`` (fewer if there are fewer): a gap or a burst moves the median little, and
    the median's quantum shrinks as much (a frame's ``t`` in seconds since the epoch is rounded
    to 0.24 us: 0.02 % of a millisecond on one interval)."""
    k = max(1, min(RATE_SPAN, inst.size - 1))
    if inst.size < 2:
        return 0.0
    med = float(np.median(inst[k:] - inst[:-k]))
    return k / med if med > 0 else 0.0


def _own_clock(log_ns: np.ndarray, t: np.ndarray | None, t0_ns: int
               ) -> tuple[np.ndarray, np.ndarray, str]:
    """``(instants, their places on the timeline, clock)`` of a key's messages in the order of
    their instants: the frames' own ``t`` (s) where at least half carry a finite one (those
    that do), else the receive times; places are receive times from ``t0_ns`` (s)."""
    at = (log_ns - t0_ns) / 1e9
    if t is not None and t.size == log_ns.size and 2 * np.count_nonzero(np.isfinite(t)) >= t.size:
        ok = np.isfinite(t)
        order = np.argsort(t[ok], kind="stable")
        return t[ok][order], at[ok][order], "frame"
    order = np.argsort(log_ns, kind="stable")
    return at[order], at[order], "receive"


def _intervals(on: np.ndarray, t_s: np.ndarray) -> list[list[float | None]]:
    """``[start, end]`` of each run of ``on`` (``end`` None: still on at the end)."""
    if not on.size:
        return []
    edges = np.diff(np.concatenate([[0], on.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [[float(t_s[s]), float(t_s[e]) if e < t_s.size else None]
            for s, e in zip(starts.tolist(), ends.tolist(), strict=True)]


def summarise(path: Path, gap_s: float | None = None) -> dict[str, Any]:
    """The summary of one recording (see the module docstring) as a JSON-ready dict.

    Raises
    ------
    DataError
        If the file cannot be read or is not MCAP.
    """
    from motcomp.record.frames import FLAG_BITS
    from motcomp.record.session import read_session

    s = read_session(path, acc=False, publish=False)
    streams: dict[str, tuple[str, np.ndarray, np.ndarray | None]] = {}
    lost: dict[str, int] = {}
    for role, st in (("input", s.inputs), ("output", s.outputs), ("feedback", s.feedback)):
        if st is not None:
            streams[st.key] = (role, st.log_ns, st.t)
    for st in (s.inputs, s.outputs):
        if st is not None:
            lost[st.key] = _lost(st.seq)
    if s.status:
        streams[s.keys["status"]] = ("status", np.array([n for n, _ in s.status], np.int64),
                                     None)
    for key, raw in s.other.items():
        streams[key] = ("", raw.log_ns, None)
    firsts = [int(ns.min()) for _, ns, _ in streams.values() if ns.size]
    lasts = [int(ns.max()) for _, ns, _ in streams.values() if ns.size]
    t0 = min(firsts) if firsts else 0
    duration = (max(lasts) - t0) / 1e9 if lasts else 0.0
    keys = []
    order = {"input": 0, "output": 1, "feedback": 2, "status": 3}
    for key, (role, ns, t) in sorted(streams.items(), key=lambda kv: (order.get(kv[1][0], 4),
                                                                      kv[0])):
        inst, at, clock = _own_clock(ns, t, t0)
        span = float(inst[-1] - inst[0]) if inst.size > 1 else 0.0
        keys.append({"key": key, "role": role, "messages": int(ns.size), "clock": clock,
                     "lost": lost.get(key),
                     "rate_hz": _rate_hz(inst),
                     "mean_rate_hz": (inst.size - 1) / span if span > 0 else 0.0,
                     "first_s": (int(ns.min()) - t0) / 1e9 if ns.size else None,
                     "last_s": (int(ns.max()) - t0) / 1e9 if ns.size else None,
                     "gaps": _gaps(inst, at, gap_s)})
    every = np.sort(np.concatenate([ns for _, ns, _ in streams.values()])) if streams else \
        np.zeros(0, np.int64)
    stall = None
    if every.size > 1:
        k = int(np.argmax(np.diff(every)))
        stall = {"longest_s": float(every[k + 1] - every[k]) / 1e9,
                 "at_s": float(every[k] - t0) / 1e9}
    modes: dict[str, Any] = {"bypass": {}, "stale": [], "rejoin": [], "parking": [],
                             "saturated_outputs": {}}
    out = s.outputs
    if out is not None and len(out):
        ok = out.valid
        flags, t_s = out.flags[ok], (out.log_ns[ok] - t0) / 1e9
        by_time = np.argsort(t_s, kind="stable")
        flags, t_s = flags[by_time], t_s[by_time]
        for axis in AXES:
            runs = _intervals((flags & FLAG_BITS[f"bypass:{axis}"]) != 0, t_s)
            if runs:
                modes["bypass"][axis] = runs
            n_sat = int(np.count_nonzero(flags & FLAG_BITS[f"sat:{axis}"]))
            if n_sat:
                modes["saturated_outputs"][axis] = n_sat
        for mode in ("stale", "rejoin", "parking"):
            modes[mode] = _intervals((flags & FLAG_BITS[mode]) != 0, t_s)
        modes["first_output_s"] = float(t_s[0])
        modes["first_input_wait"] = _first_input_wait(modes["stale"], s.status, t0)
        if modes["first_input_wait"] is not None:
            modes["stale"] = modes["stale"][1:]
    meta = s.metadata
    return {
        "file": s.name,
        "duration_s": duration,
        "messages": s.messages,
        "config_hash": meta.get("config_hash") or next(iter(s.config_hashes()), None),
        "config_hashes": s.config_hashes(),
        "recorded_config": s.config_json is not None,
        "metadata": meta,
        "platform": _last_platform(s.status),
        "model_mismatch": _mismatch(s.status, t0),
        "keys": keys,
        "recorder_stall": stall,
        "modes": modes,
        "truncated": s.truncated,
        "damaged": s.damaged,
        "warnings": list(s.warnings),
    }


def _first_input_wait(stale: list[list[float | None]], status: list[tuple[int, dict[str, Any]]],
                      t0: int) -> list[float | None] | None:
    """The first stale run if it was the service's wait for its first input frame, not an
    input lost: the service's status counts no episode there (``stale_episodes`` leaves that
    wait out, docs/WIRE.md).  Judged on the first status frame recorded after the run ends (or
    during it, if it never ends) and before the next run starts; None without one."""
    if not stale:
        return None
    start, end = stale[0]
    assert start is not None
    upto = stale[1][0] if len(stale) > 1 else None
    for ns, st in status:
        t = (ns - t0) / 1e9
        if t < (start if end is None else end):
            continue
        if upto is not None and t >= upto:
            return None
        n = st.get("stale_episodes")
        return stale[0] if isinstance(n, int) and not isinstance(n, bool) and n == 0 else None
    return None


def _last_platform(status: list[tuple[int, dict[str, Any]]]) -> dict[str, Any] | None:
    """The platform's figures in the last recorded service status that carries them."""
    for _, st in reversed(status):
        plat = st.get("platform")
        if isinstance(plat, dict) and plat:
            return {**plat, "status_t": st.get("t", 0.0)}
    return None


def _mismatch(status: list[tuple[int, dict[str, Any]]], t0: int) -> dict[str, Any]:
    """Per supervised axis, from the recorded service status frames (docs/SUPERVISION.md):
    the stretches its model-mismatch alarm was on (s from the recording's start; an end of
    None: still on at the end), the estimates' residual delay at the alarm's start, and the
    last estimate."""
    on: dict[str, list[list[float | None]]] = {}
    at_start: dict[str, list[float | None]] = {}
    last: dict[str, Any] = {}
    for ns, st in status:
        block = st.get("model_mismatch")
        if not isinstance(block, dict) or not isinstance(block.get("axes"), dict):
            continue
        t = (ns - t0) / 1e9
        for axis, fig in block["axes"].items():
            if not isinstance(fig, dict):
                continue
            runs = on.setdefault(axis, [])
            if fig.get("alarm") and (not runs or runs[-1][1] is not None):
                runs.append([t, None])
                at_start.setdefault(axis, []).append(fig.get("residual_delay_ms"))
            elif not fig.get("alarm") and runs and runs[-1][1] is None:
                runs[-1][1] = t
            if isinstance(fig.get("estimate"), dict):
                last[axis] = {"spec": fig["estimate"].get("spec"),
                              "residual_delay_ms": fig.get("residual_delay_ms"),
                              "informative": fig.get("informative"),
                              "reason": fig.get("reason"), "t_s": t,
                              "windows": fig.get("windows"),
                              "informative_windows": fig.get("informative_windows")}
    return {a: {"alarms": on.get(a, []), "residual_delay_ms_at_alarm": at_start.get(a, []),
                "last_estimate": last.get(a)} for a in sorted(set(on) | set(last))}


def _mismatch_text(mm: dict[str, Any]) -> str:
    """An axis' supervision in a recording: its alarms, or that none was raised and on how many
    judged windows -- "no alarm" on windows none of which was judged is said as such -- and its
    last estimate, with why it was not judged where it was not."""
    runs = mm["alarms"]
    est = mm["last_estimate"] or {}
    windows, judged = est.get("windows"), est.get("informative_windows")
    if runs:
        text = f"mismatch alarm {len(runs)}: " + ", ".join(
            f"{_span(r)} (residual {d:+.1f} ms)" if isinstance(d, int | float) else _span(r)
            for r, d in zip(runs, mm["residual_delay_ms_at_alarm"], strict=False))
    elif isinstance(windows, int) and judged == 0:
        text = f"not supervised: none of its {windows} windows judged, no alarm possible"
    else:
        text = "no mismatch alarm" + (f" ({judged} of {windows} windows judged)"
                                      if isinstance(windows, int) and isinstance(judged, int)
                                      else "")
    if est.get("spec"):
        text += f"; last estimate {est['spec']}"
        if est.get("informative") is False:
            text += f" (not judged: {est['reason']})" if est.get("reason") else " (not judged)"
    return text


def _span(run: list[float | None]) -> str:
    start, end = run
    assert start is not None
    return f"{start:.2f}-{end:.2f} s" if end is not None else f"{start:.2f} s-end"


def rejoins_unseen(modes: dict[str, Any], tol_s: float = 0.05) -> int:
    """The rejoins no recorded stale output ends: the input went stale and came back while the
    loop stalled, between two outputs (the service's log says "stale ... briefly"), or the
    outputs that showed it were lost.  A rejoin going on when the recording began is not one."""
    ends = [r[1] for r in [*modes["stale"], modes.get("first_input_wait") or [None, None]]
            if r[1] is not None]
    first = modes.get("first_output_s", -math.inf)
    return sum(1 for r in modes["rejoin"]
               if r[0] > first + tol_s and not any(abs(e - r[0]) <= tol_s for e in ends))


def format_info(info: dict[str, Any]) -> str:
    """:func:`summarise`'s dict as text."""
    meta = info["metadata"]
    head = f"{info['file']}: {info['duration_s']:.1f} s, {info['messages']} messages"
    if meta.get("version"):
        head += f" (motcomp {meta['version']}"
        head += f", started {meta['started']})" if meta.get("started") else ")"
    later = [h for h in info.get("config_hashes", []) if h != info["config_hash"]]
    lines = [head, f"config hash {info['config_hash'] or 'unknown'}"
             + (f", then {', '.join(later)} (reloaded during the recording)" if later else "")
             + ("" if info["recorded_config"] else
                " (no config recorded" + (f": {meta['config_missing']})"
                                          if meta.get("config_missing") else ")"))]
    if info.get("platform"):
        from motcomp.cli.admin import platform_line

        plat = info["platform"]
        lines.append(platform_line(plat, float(plat.get("status_t", 0.0))))
    lines.append(f"{'key':<28}{'role':<10}{'messages':>9}{'lost':>7}{'rate Hz':>10}{'gaps':>6}"
                 "  longest gap")
    for k in info["keys"]:
        g = k["gaps"]
        longest = (f"{g['longest_s']:.3f} s at {g['longest_at_s']:.2f} s" if g["count"] else "-")
        rate = f"{k['rate_hz']:.1f}" if math.isfinite(k["rate_hz"]) else "-"
        lost_n = "-" if k.get("lost") is None else str(k["lost"])
        lines.append(f"{k['key']:<28}{k['role'] or '-':<10}{k['messages']:>9}{lost_n:>7}"
                     f"{rate:>10}{g['count']:>6}  {longest}")
    clocks = {k["clock"] for k in info["keys"] if k["role"] in ("input", "output", "feedback")}
    if clocks:
        lines.append("(lost: the seq numbers missing; rate: the median over runs of "
                     f"{RATE_SPAN} intervals, gaps left out; rates and gaps on the frames' own t"
                     + (
            "; a key whose frames carry none on the receive times)" if "receive" in clocks
            else ")"))
    stall = info.get("recorder_stall")
    if stall and stall["longest_s"] > MIN_GAP_S:
        lines.append(f"recorder: received nothing for {stall['longest_s']:.3f} s at "
                     f"{stall['at_s']:.2f} s (the longest stretch; where the frames' t show no "
                     f"gap there, its host stalled it and the frames came in a burst)")
    modes = info["modes"]
    if any(k["messages"] for k in info["keys"] if k["role"] == "output"):
        lines.append("mode switches (output flags):")
        groups: dict[str, list[str]] = {}  # axes with the same switches on one line
        for axis, runs in modes["bypass"].items():
            text = ", ".join(f"on {'from the start' if r[0] == 0 else f'at {r[0]:.2f} s'}"
                             + ("" if r[1] is None else f", off at {r[1]:.2f} s") for r in runs)
            groups.setdefault(text, []).append(axis)
        for text, axes in groups.items():
            lines.append(f"  bypass     {', '.join(axes)}: {text}")
        if not groups:
            lines.append("  bypass     none")
        unseen = rejoins_unseen(modes)
        wait = modes.get("first_input_wait")
        if wait is not None:
            lines.append(f"  no input   {_span(wait)} (the service waiting for its first frame)")
        for mode in ("stale", "rejoin", "parking"):
            runs = modes[mode]
            lines.append(f"  {mode:<10} " + (
                f"{len(runs)}: " + ", ".join(_span(r) for r in runs[:8])
                + (", ..." if len(runs) > 8 else "") if runs else "none")
                + (f" ({unseen} after a stale input no recorded output shows: the loop stalled "
                   "through it, between two outputs, or those that showed it were lost)"
                   if mode == "rejoin" and unseen else ""))
    else:  # nothing to tell the modes from: not "none"
        lines.append("mode switches: unknown, no output frames recorded (a service whose output "
                     "goes over CAN alone sends none on zenoh: output.transport = \"both\")")
    for axis, mm in (info.get("model_mismatch") or {}).items():
        lines.append(f"  model      {axis}: {_mismatch_text(mm)}")
    sat = modes["saturated_outputs"]
    lines.append("saturated outputs: " + (", ".join(f"{a} {n}" for a, n in sat.items())
                                          if sat else "none"))
    if info["truncated"]:
        lines.append("warning: damaged recording (read up to the chunk before the damage)"
                     if info["damaged"] else
                     "warning: unfinished recording (read up to its last complete chunk)")
    lines += [f"warning: {w}" for w in info["warnings"]]
    return "\n".join(lines)
