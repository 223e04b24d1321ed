"""Example client of the motcomp wire contract (docs/WIRE.md), using only zenoh and msgpack.

Publishes a 0.25 Hz lateral sine as setpoint frames at 500 Hz for a few seconds, prints the
corrected setpoints coming back and the service's status.  Run it against a service:

    motcomp run --config config/motcomp.toml          # listens on tcp/127.0.0.1:7447
    python tools/example_client.py -e tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import json
import math
import time

import msgpack
import zenoh


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("-e", "--connect", action="append", default=[], help="service endpoint")
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(args.connect or ["tcp/127.0.0.1:7447"]))
    with zenoh.open(conf) as session:
        pub = session.declare_publisher("sim/motion/setpoint")
        outputs = session.declare_subscriber("platform/setpoint", zenoh.handlers.RingChannel(1))
        t0 = time.time()
        k = 0
        next_print = t0
        while (now := time.time()) - t0 < args.seconds:
            k = max(k, int((now - t0) * 500.0))  # behind (a stall): skip to the current sample
            t = k / 500.0
            y = 0.3 * math.sin(2 * math.pi * 0.25 * t)
            frame = {"seq": k, "t": t0 + t, "pos": {"rails_y": y}}
            pub.put(msgpack.packb(frame))
            k += 1
            if now >= next_print and (s := outputs.try_recv()) is not None:
                out = msgpack.unpackb(s.payload.to_bytes())
                print(f"sent rails_y={frame['pos']['rails_y']:+.4f} m  ->  platform gets "
                      f"{out['pos']['rails_y']:+.4f} m  (seq {out['seq']}, from input "
                      f"{out['src_seq']}, flags {out['flags']})")
                next_print = now + 0.5
            time.sleep(max(0.0, t0 + (k / 500.0) - time.time()))
        for reply in session.get("motcomp/status", timeout=2.0):
            if reply.ok is not None:
                st = msgpack.unpackb(reply.ok.payload.to_bytes())
                print(f"status: mode {st['mode']}, {st['frames']['accepted']} frames accepted, "
                      f"{st['frames']['rejected']} rejected, loop p99 "
                      f"{st['loop'].get('compute_p99_us', float('nan')):.0f} us")
        outputs.undeclare()
        pub.undeclare()


if __name__ == "__main__":
    main()
