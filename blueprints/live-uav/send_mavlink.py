"""A scripted vehicle for the live-uav blueprint: flies the Central Park route (scene
frame) at ``--speed`` m/s and streams MAVLink LOCAL_POSITION_NED (NED: x north, y east,
z down, origin at the scene's origin) at ``--rate`` Hz to ``--to`` over UDP, as PX4 or
ArduPilot SITL would.

    .venv/bin/python blueprints/live-uav/send_mavlink.py [--to 127.0.0.1:14550] [--speed 10] [--rate 20]
"""

from __future__ import annotations

import argparse
import socket
import sys
import time

import numpy as np
from pymavlink.dialects.v20 import all as mavlink

from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--to", default="127.0.0.1:14550", help="UDP host:port of the twin")
    ap.add_argument("--speed", type=float, default=10.0, help="m/s along the route")
    ap.add_argument("--rate", type=float, default=20.0, help="messages per second")
    ap.add_argument("--system", type=int, default=1, help="MAVLink system ID")
    ap.add_argument("--seconds", type=float, default=None, help="stop after this long (default: the route's end)")
    args = ap.parse_args(argv)
    host, port = args.to.rsplit(":", 1)
    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    seconds = args.seconds if args.seconds is not None else route.length / args.speed
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink.MAVLink(None, srcSystem=args.system, srcComponent=1)
    print(f"sending LOCAL_POSITION_NED to {host}:{port} at {args.rate:g} Hz for {seconds:.0f} s", file=sys.stderr)
    t0 = time.monotonic()
    k = 0
    while (t := time.monotonic() - t0) < seconds:
        e, n, u = route.at(min(t * args.speed, route.length))
        ve, vn, vu = (route.at(min((t + 0.1) * args.speed, route.length)) - np.array([e, n, u])) / 0.1
        msg = mav.local_position_ned_encode(int(t * 1e3), n, e, -u, vn, ve, -vu)
        sock.sendto(msg.pack(mav), (host, int(port)))
        mav.seq = (mav.seq + 1) % 256
        k += 1
        time.sleep(max(0.0, t0 + k / args.rate - time.monotonic()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
