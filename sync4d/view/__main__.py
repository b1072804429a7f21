"""Serve the viewer: ``python -m sync4d.view RUN [RUN ...] [--port P] [--host H] [--fps F] [--play]
[--max-gaussians M]``."""

from __future__ import annotations

import argparse
import sys

from sync4d.errors import Sync4DError


def parse(argv: list[str] | None) -> argparse.Namespace:
    from sync4d.view.app import ViewerConfig

    d = ViewerConfig()  # the defaults live there
    parser = argparse.ArgumentParser(prog="python -m sync4d.view", description=__doc__)
    parser.add_argument("runs", nargs="+", help="run folders (outputs/<name>/<timestamp>), one row each")
    parser.add_argument("--port", type=int, default=d.port, help=f"HTTP/websocket port ({d.port})")
    parser.add_argument("--host", default=d.host, help=f"interface ({d.host}: this machine only)")
    parser.add_argument("--fps", type=float, default=d.fps, help="playback rate; 0 = the run's")
    parser.add_argument("--play", action="store_true", default=d.play, help="start playing")
    parser.add_argument("--max-gaussians", type=int, default=d.max_gaussians,
                        help=f"show a fixed random subset of larger objects ({d.max_gaussians})")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Open the runs and serve until interrupted; a bad folder or option prints one line and returns 2."""
    from sync4d.view.app import Viewer, ViewerConfig
    from sync4d.view.data import load_run

    args = parse(argv)
    try:
        runs = [load_run(folder) for folder in args.runs]
        viewer = Viewer(runs, ViewerConfig(host=args.host, port=args.port, fps=args.fps, play=args.play,
                                             max_gaussians=args.max_gaussians))
    except Sync4DError as err:
        print(f"sync4d.view: {type(err).__name__}: {err}", file=sys.stderr)
        return 2
    print(f"sync4d.view: serving {len(runs)} run(s), {viewer.num_frames} frames, at http://{args.host}:{viewer.port}",
          flush=True)
    viewer.serve_forever()
    return 0


if __name__ == "__main__":
    sys.exit(main())
