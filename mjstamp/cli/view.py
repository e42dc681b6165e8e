"""`mjstamp view`: the plans of a results directory played in meshcat (live or HTML)."""

from __future__ import annotations

import sys

from mjstamp.errors import MjstampError


def add_parser(subparsers):
    """Adds `view` to `subparsers`; returns its parser."""
    view = subparsers.add_parser(
        "view", help="play the plans of a results directory in meshcat (live or HTML)"
    )
    view.add_argument("dir", help="results directory written by `mjstamp solve --out`")
    which = view.add_mutually_exclusive_group()
    which.add_argument("--plan", type=int, action="append", metavar="N",
                       help="play the returned plan of particle N (repeatable); "
                       "default: the best verified plan of each task plan")
    which.add_argument("--task-plan", metavar="NAME",
                       help="play every verified plan of this task plan (e.g. 0110-top)")
    view.add_argument("--task", metavar="NAME",
                      help="check that DIR holds plans of this task")
    view.add_argument("--html", metavar="OUT.html",
                      help="write a standalone page that plays offline, instead of a server")
    view.add_argument("--perturbed", type=int, nargs="?", const=8, default=0, metavar="N",
                      help="play N (default 8) of each plan's perturbed replays (the draws "
                      "of its robustness score) beside it, as translucent copies")
    view.add_argument("--port", type=int, default=None,
                      help="web port of the meshcat server (default: first free from 7000)")
    view.add_argument("--no-browser", action="store_true",
                      help="do not open the viewer in a browser")
    view.set_defaults(func=run)
    return view


def run(args) -> int:
    """Writes the HTML page, or serves the plans until Ctrl-C or SIGTERM."""
    import signal
    import time

    from mjstamp import viz

    if args.port is not None and not 0 < args.port < 65536:
        raise MjstampError(f"--port={args.port} must be in 1..65535")
    if args.perturbed < 0:
        raise MjstampError(f"--perturbed={args.perturbed} must be >= 0 (replays per plan)")
    choice = dict(plan=args.plan, task_plan=args.task_plan, task=args.task,
                  perturbed=args.perturbed)
    if args.html:
        playback = viz.write_html(args.dir, args.html, **choice)
        print(f"wrote {playback.html} ({len(playback.segments)} plans)", file=sys.stderr)
        return 0
    # ServerUnavailable is an MjstampError: main prints its one line (where the
    # fallback page went) and exits with status 2.
    playback = viz.play(args.dir, port=args.port, open_browser=not args.no_browser, **choice)
    print(f"meshcat viewer: {playback.url} (Ctrl-C to stop)", flush=True)
    for segment in playback.segments:
        print(f"  {segment.label()}", flush=True)

    def stop(signum, frame):  # SIGTERM ends the viewer like Ctrl-C, server included
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0
    finally:
        playback.close()
