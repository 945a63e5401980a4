"""``caviar-core view RUN_DIR [--port P] [--host H]``: serves the live and replay view
of a run directory until Ctrl-C."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    """``argv``: the arguments after ``view`` (default ``sys.argv[1:]``). Returns the
    exit status: 0 after Ctrl-C, 2 for a missing or unreadable run directory or a port
    that cannot be bound."""
    ap = argparse.ArgumentParser(prog="caviar-core view",
                                 description="Watch a run in the browser: 3D scene, timeline, plots. "
                                             "Follows a run that is still going.")
    ap.add_argument("run_dir", metavar="RUN_DIR", help="a run directory written by `caviar-core run`")
    ap.add_argument("--port", type=int, default=8765, help="port (default 8765; 0 picks a free one)")
    ap.add_argument("--host", default="127.0.0.1",
                    help="address to bind (default 127.0.0.1: this machine only; the server is read-only)")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)

    from caviar.view.data import RunDirError
    from caviar.view.server import make_server

    try:
        httpd, state = make_server(args.run_dir, args.host, args.port)
    except RunDirError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # port in use, address not available
        print(f"error: cannot listen on {args.host}:{args.port}: {e.strerror or e}", file=sys.stderr)
        return 2
    d = state.data
    print(f"view of {d.path} ({d.status.get('status')}, {len(d.step_time)} steps): {httpd.url}  (Ctrl-C stops)",
          flush=True)
    try:
        httpd.serve_forever(poll_interval=0.25)
    except KeyboardInterrupt:
        pass
    finally:
        state.stopping.set()
        httpd.server_close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
