"""``motcomp excite``: an identification signal for one axis, within its limits."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from motcomp.cli._common import (
    finite_float,
    non_negative_float,
    non_negative_int,
    positive_float,
    print_json,
    rate_arg,
)
from motcomp.core.axes import AXIS_INDEX
from motcomp.errors import ConfigError

if TYPE_CHECKING:
    from motcomp.ident.excitation import AxisRange

ORDER = 4


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "excite", help="generate an identification signal (noise, sweep, multisine)",
        description="Generate an excitation for one axis, scaled to its position, velocity and "
                    "acceleration limits (checked on the samples), starting and ending at "
                    "neutral.  Writes STEM.csv (t,cmd) and STEM.msgpack (the service's setpoint "
                    "frames, concatenated).  With --simulate, also a synthetic recording "
                    "STEM.sim.csv (t,cmd,acc) of a simulated platform.")
    p.add_argument("--axis", required=True, metavar="NAME", help="axis, e.g. rails_y or hex_z")
    p.add_argument("--kind", choices=("noise", "sweep", "multisine"), default="noise",
                   help="signal kind (default: noise, low-pass pseudo-white)")
    p.add_argument("--duration", type=positive_float, default=60.0, metavar="S",
                   help="total duration including holds and fades (default: 60)")
    p.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ",
                   help="sample rate (default: 1000)")
    p.add_argument("--band", type=rate_arg, default=None, metavar="HZ",
                   help="noise band and default sweep/multisine top (default: 4 rails, 10 hexapod)")
    p.add_argument("--f-min", type=rate_arg, default=0.1, metavar="HZ",
                   help="sweep/multisine lowest frequency (default: 0.1)")
    p.add_argument("--f-max", type=rate_arg, default=None, metavar="HZ",
                   help="sweep/multisine highest frequency (default: the band)")
    p.add_argument("--period", type=positive_float, default=None, metavar="S",
                   help="multisine period (default: 1/f-min)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="noise seed (default: 0)")
    p.add_argument("--usage", type=positive_float, default=0.9, metavar="FRACTION",
                   help="fraction of the tightest limit to reach (default: 0.9)")
    p.add_argument("--fade", type=non_negative_float, default=2.0, metavar="S",
                   help="raised-cosine fade in and out (default: 2)")
    p.add_argument("--hold", type=non_negative_float, default=0.5, metavar="S",
                   help="neutral hold at both ends (default: 0.5)")
    p.add_argument("--plant", metavar="NAME",
                   help="preset whose limits apply (default: rails for rails_*, hexapod for hex_*)")
    p.add_argument("--limits", nargs=3, type=finite_float, metavar=("POS", "VEL", "ACC"),
                   help="symmetric limits instead of a preset's")
    p.add_argument("--out", type=Path, required=True, metavar="STEM",
                   help="output path without suffix")
    p.add_argument("--simulate", metavar="SPEC|PRESET",
                   help="also write STEM.sim.csv: this model's response as an accelerometer "
                        "records it")
    p.add_argument("--snr", type=finite_float, default=10.0, metavar="DB",
                   help="with --simulate: signal-to-disturbance ratio, noise + tremor (default 10)")
    p.add_argument("--jitter-ms", type=non_negative_float, default=0.0, metavar="MS",
                   help="with --simulate: time-stamp jitter (default: 0)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument("--quiet", action="store_true",
                   help="no progress on stderr (a bar on a terminal, else plain lines)")
    p.set_defaults(func=run_excite)


def _limits(args: argparse.Namespace) -> tuple[AxisRange, str | None]:
    from motcomp.ident.excitation import AxisRange
    from motcomp.presets import load_preset

    if args.limits:
        pos, vel, acc = args.limits
        return AxisRange(-pos, pos, vel, acc), None
    name = args.plant or ("rails" if args.axis.startswith("rails") else "hexapod")
    preset = load_preset(name)
    lim = preset.axis_limits(args.axis)
    return AxisRange(float(lim.p_min[0]), float(lim.p_max[0]), float(lim.v_max[0]),
                     float(lim.a_max[0])), preset.name


def run_excite(args: argparse.Namespace) -> int:
    import numpy as np

    from motcomp.ident.excitation import excitation, write_csv, write_setpoint_stream

    if args.axis not in AXIS_INDEX:
        raise ConfigError(f"--axis: unknown axis {args.axis!r}; axes are {', '.join(AXIS_INDEX)}")
    limits, preset = _limits(args)
    from motcomp.progress import Progress

    with Progress(f"excite {args.kind}", total=1.0, quiet=args.quiet):
        exc = excitation(args.kind, args.axis, limits, duration_s=args.duration,
                         rate_hz=args.rate, band_hz=args.band, f_min_hz=args.f_min,
                         f_max_hz=args.f_max, seed=args.seed, usage=args.usage, fade_s=args.fade,
                         hold_s=args.hold, period_s=args.period)
    sim = None
    if args.simulate:
        from motcomp.core.models import parse_model
        from motcomp.ident.data import write_recording_csv
        from motcomp.presets import load_preset
        from motcomp.sim.platform import Accelerometer, record_identification, true_acceleration

        model = parse_model(args.simulate) if ":" in args.simulate else \
            load_preset(args.simulate).model
        if not math.isfinite(args.snr) or args.jitter_ms < 0 or not math.isfinite(args.jitter_ms):
            raise ConfigError(f"--snr must be finite and --jitter-ms >= 0, got {args.snr}, "
                              f"{args.jitter_ms}")
        rms = float(np.std(true_acceleration(model, exc.cmd, exc.rate_hz)))
        meter = Accelerometer.realistic(rms, snr_db=args.snr)
        # the sensor's noise must not replay the excitation's own random numbers
        sensor_seed = int(np.random.SeedSequence([args.seed, 1]).generate_state(1)[0])
        t, cmd, acc = record_identification(model, exc.cmd, exc.rate_hz, meter,
                                            jitter_s=args.jitter_ms * 1e-3, seed=sensor_seed)
        sim = args.out.with_name(args.out.name + ".sim.csv")
    csv_path = args.out.with_name(args.out.name + ".csv")
    stream_path = args.out.with_name(args.out.name + ".msgpack")
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_csv(csv_path, exc)
        write_setpoint_stream(stream_path, exc)
        if sim is not None:
            write_recording_csv(sim, t, cmd, acc, axis=args.axis)
    except OSError as exc_os:
        raise ConfigError(f"--out {args.out}: cannot write: {exc_os.strerror or exc_os}"
                          ) from None
    files = [str(csv_path), str(stream_path)] + ([str(sim)] if sim is not None else [])
    summary = exc.summary()
    summary.update(limits_from=preset or "--limits", files=files)
    if args.json:
        print_json(summary)
    else:
        u = exc.usage
        print(f"{exc.kind} for {exc.axis}: {summary['duration_s']:.1f} s at {exc.rate_hz:g} Hz; "
              f"peaks {exc.peaks['position']:.4g} (pos), {exc.peaks['velocity']:.4g} (vel), "
              f"{exc.peaks['acceleration']:.4g} (acc) = {u['position'] * 100:.3g} %, "
              f"{u['velocity'] * 100:.3g} %, {u['acceleration'] * 100:.3g} % of the limits")
        print(f"wrote {', '.join(files)}")
    return 0
