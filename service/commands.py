"""`gradsep serve | client`: the argument parsers and their handlers; FastAPI/uvicorn/httpx are imported lazily
by the handlers, so building the parser costs nothing."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import gradsep.model.methods as table
from gradsep.model.channels import choices_text
from gradsep.model.errors import CommandError


def serve_command(args: argparse.Namespace) -> int:
    """`gradsep serve`: run the service under uvicorn with settings validated up front."""
    from gradsep.service.serve import serve

    serve(args.host, args.port, args.workers)
    return 0


def client_command(args: argparse.Namespace, *, sleep: Callable[[float], None] = time.sleep) -> int:
    """`gradsep client FRAME -o OUT`: post the frame, write the answer atomically; the exit status of
    service.client.send_frame (0 written, 2 bad input or 4xx, 75 unavailable, 1 service failure)."""
    from gradsep.service.client import ClientOptions, Shot, send_frame, send_shot

    params = {"method": args.method, "alpha": args.alpha, "format": args.format, "layers": args.layers,
              "channels": getattr(args, "channels", None)}
    options = ClientOptions(args.url, args.token, params, args.retries, args.timeout)
    if getattr(args, "frames", None) is None:
        if getattr(args, "window", None) is not None:
            raise CommandError("--window needs --frames A-B (a shot posted window by window)")
        return send_frame(Path(args.frame), Path(args.output), options, sleep)
    from gradsep.model.shot import FramePattern, parse_frames
    from gradsep.model.temporal import DEFAULT_WINDOW

    shot = Shot(FramePattern(args.frame).require_field("input"), FramePattern(args.output).require_field("output"),
                parse_frames(args.frames), DEFAULT_WINDOW if args.window is None else args.window)
    return send_shot(shot, options, sleep)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the HTTP reconstruction service (uvicorn)")
    p.add_argument("--host", default="0.0.0.0")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1)
    p.set_defaults(func=serve_command)

    p = sub.add_parser("client", help="post a frame to the service and write the reconstruction (render-farm task)")
    p.add_argument("frame", help="input frame (.exr); with --frames a pattern ('shot.%%04d.exr' or shot.####.exr)")
    p.add_argument("-o", "--output", required=True, help="output .exr (with --frames a pattern), written atomically")
    p.add_argument("--frames", default=None, metavar="A-B",
                   help="post the shot's frames A-B, each with its window of neighbours (temporal reconstruction)")
    p.add_argument("--window", type=int, default=None, metavar="N",
                   help="frames per window with --frames (odd; default 5)")
    p.add_argument("--url", default=None, help="service base URL (default: $GRADSEP_URL or http://127.0.0.1:8000)")
    p.add_argument("--method", choices=table.names(), default=None,
                   help="reconstruction method (default: the service picks the best it serves for the frame)")
    p.add_argument("--alpha", type=float, default=None)
    p.add_argument("--format", choices=("half", "float"), default=None)
    p.add_argument("--layers", choices=("sum", "all"), default=None)
    p.add_argument("--channels", default=None, metavar="LAYOUT",
                   help=f"channel layout of the frame ({choices_text()}; default: the service detects it)")
    p.add_argument("--retries", type=int, default=5, help="retries on 503 and connection errors")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per request")
    p.add_argument("--token", default=None, help="bearer token (or $GRADSEP_TOKEN)")
    p.set_defaults(func=client_command)
