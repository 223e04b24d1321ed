"""Benchmark: offline replay of one-hour, 8-axis, 1 kHz sessions through the service's tick.

1. Two one-hour recordings, made once by ``motcomp.replay.synth`` (the tick itself on virtual
   time: a source publishing all 8 axes at 1 kHz with 60-400 us transit jitter and a clock
   20 ppm fast, the outputs of config/motcomp.toml -- rails ZN, hexapod bypassed --, the
   platform's feedback from the plant models, a status frame a second) and cached under
   ``out/`` (gitignored; delete them to regenerate, several minutes each).
2. ``motcomp replay A --json --quiet`` (one core) and ``motcomp replay A B --jobs 2 --json
   --quiet`` as subprocesses, ``--runs`` times each: medians of the wall time of the whole
   command (start-up, imports, reading, plan, tick, analysis) and the speed-up over real time.
   Target: one hour in <= 120 s on one core (30x).
3. Agreement: a 60 s session with stalls (catch-up), a bypass switched off and on, a silent
   gap, a 0.3 m step, partial frames, frames without ``t``, bad frames and parking, replayed:
   bit for bit the recorded outputs.

Usage: ``python tools/bench_replay.py [--runs 3] [--write-doc]``; ``--write-doc`` replaces the
"replay" section of docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _bench import machine, write_section

from motcomp.config import load_config, resolve_axes
from motcomp.record import read_session
from motcomp.replay.engine import run_ticks
from motcomp.replay.offline import plan_for
from motcomp.replay.synth import SynthOptions, synthesize
from motcomp.resources import config_file

OUT = Path(__file__).resolve().parent.parent / "out"
RICH = SynthOptions(duration_s=60.0, seed=11, stalls=[(12.5, 3), (31.0, 30)],
                    gaps=[(20.0, 0.4)], bypass=[(25.0, True, ("rails_x",)),
                                                (40.0, False, ("rails_x",))],
                    steps=[(45.0, "rails_y", 0.3)], partial_every=7, bad_every=97,
                    no_t_every=13, park_at_s=58.0)


def hour_session(path: Path, seed: int) -> float:
    """Synthesize the hour into ``path`` unless it is there; seconds spent."""
    if path.exists():
        return 0.0
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    tmp = path.with_suffix(".part")
    synthesize(tmp, load_config(config_file("motcomp.toml")),
               SynthOptions(duration_s=3600.0, seed=seed))
    tmp.rename(path)
    return time.perf_counter() - t0


def replay_cmd(paths: list[Path], jobs: int, runs: int) -> tuple[list[float], object]:
    """Wall times of ``runs`` runs of ``motcomp replay`` and the JSON of the last."""
    walls, out = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "motcomp", "replay", *map(str, paths),
                            "--jobs", str(jobs), "--json", "--quiet"],
                           capture_output=True, text=True, check=True)
        walls.append(time.perf_counter() - t0)
        out = json.loads(p.stdout)
    return walls, out


def agreement(tmp: Path) -> dict[str, float]:
    cfg = load_config(config_file("motcomp.toml"))
    path = tmp / "rich.mcap"
    synthesize(path, cfg, RICH)
    s = read_session(path)
    assert s.inputs is not None and s.outputs is not None
    plan = plan_for(s, cfg, resolve_axes(cfg))
    t0 = time.perf_counter()
    res = run_ticks(plan, s.inputs, cfg)
    dt = time.perf_counter() - t0
    rows = np.flatnonzero(plan.output >= 0)
    rec = s.outputs.pos[plan.output[rows]]
    return {"rows": plan.rows, "catch_up": int((~plan.emit).sum()),
            "equal": float(np.array_equal(res.u[rows], rec)),
            "max_diff": float(np.abs(res.u[rows] - rec).max()),
            "saturated": int(res.limited[rows].sum()), "us_per_tick": dt / rows.size * 1e6}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--write-doc", action="store_true",
                    help="replace the replay section of docs/BENCHMARKS.md")
    args = ap.parse_args()
    head = machine()
    files = [OUT / "bench-replay-hour-a.mcap", OUT / "bench-replay-hour-b.mcap"]
    for f, seed in zip(files, (3, 4), strict=True):
        gen = hour_session(f, seed)
        made = f", generated in {gen:.0f} s" if gen else " (cached)"
        print(f"session {f} ({f.stat().st_size / 1e9:.2f} GB){made}", flush=True)
    walls1, one = replay_cmd(files[:1], 1, args.runs)
    walls2, two = replay_cmd(files, 2, args.runs)
    assert isinstance(one, dict) and isinstance(two, list)
    session_s = float(one["session_s"])
    tim = one["runs"][0]["timings"]
    with tempfile.TemporaryDirectory() as tmp:
        agr = agreement(Path(tmp))
    rails = {a["axis"]: a for a in one["runs"][0]["axes"]}
    m1, m2 = statistics.median(walls1), statistics.median(walls2)
    load = os.getloadavg()
    lines = [
        f"Machine: {head}.",
        "",
        f"`python tools/bench_replay.py --runs {args.runs}`: `motcomp replay` on one-hour, "
        f"8-axis, 1 kHz recordings ({one['ticks']} ticks each; made by `motcomp.replay.synth`: "
        "jittery 1 kHz source with a drifting clock, the tick's outputs, simulated feedback), "
        "as a subprocess: wall time of the whole command (start-up, imports, reading, plan, "
        "the tick, analysis).",
        "",
        "| | runs (s) | median (s) | speed-up (median) |",
        "|---|---|---|---|",
        f"| 1 file, 1 core | {', '.join(f'{w:.1f}' for w in walls1)} | {m1:.1f} | "
        f"{session_s / m1:.0f}x |",
        f"| 2 files, `--jobs 2` | {', '.join(f'{w:.1f}' for w in walls2)} | {m2:.1f} | "
        f"{2 * session_s / m2:.0f}x |",
        "",
        f"Breakdown of the last 1-file run (in-process): reading {one['read_s']:.1f} s, tick "
        f"plan {tim['plan_s']:.1f} s, the tick {tim['engine_s']:.1f} s "
        f"({tim['us_per_tick']:.1f} us a tick), analysis {tim['analysis_s']:.1f} s.  Target: "
        "<= 120 s (30x) on one core.  Load average after the runs: "
        f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}.",
        "",
        f"Replayed vs recorded outputs over the hour: max |diff| rails_x "
        f"{rails['rails_x']['max_diff']:.1e} m, rails_y {rails['rails_y']['max_diff']:.1e} m.",
        "",
        f"A 60 s session with stalls ({agr['catch_up']} catch-up steps), a bypass switched off "
        "and on, a silent gap, a 0.3 m step, partial frames, frames without t, bad frames and "
        f"parking ({agr['rows']} steps, {agr['saturated']} saturated samples): replayed "
        f"{'bit for bit' if agr['equal'] else 'NOT bit for bit'} (max |diff| "
        f"{agr['max_diff']:.1e}), {agr['us_per_tick']:.1f} us a tick.",
    ]
    text = "\n".join(lines)
    print(text)
    if args.write_doc:
        write_section("replay", text)


if __name__ == "__main__":
    main()
