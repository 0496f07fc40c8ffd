"""`gradsep serve | client`: argparse only; handlers import FastAPI/httpx lazily."""

from __future__ import annotations

import argparse

from model.policy import METHODS


def _serve(args: argparse.Namespace) -> int:
    from service.serve import serve_command

    return serve_command(args)


def _client(args: argparse.Namespace) -> int:
    from service.client import client_command

    return client_command(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the HTTP reconstruction service (uvicorn)")
    p.add_argument("--host", default="0.0.0.0")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1)
    p.set_defaults(func=_serve)

    p = sub.add_parser("client", help="post a frame to the service and write the reconstruction (render-farm task)")
    p.add_argument("frame", help="input frame (.exr)")
    p.add_argument("-o", "--output", required=True, help="output .exr, written atomically")
    p.add_argument("--url", default=None, help="service base URL (default: $GRADSEP_URL or http://127.0.0.1:8000)")
    p.add_argument("--method", choices=METHODS, default=None,
                   help="reconstruction method (default: the service picks the best it serves for the frame)")
    p.add_argument("--alpha", type=float, default=None)
    p.add_argument("--format", choices=("half", "float"), default=None)
    p.add_argument("--layers", choices=("sum", "all"), default=None)
    p.add_argument("--retries", type=int, default=5, help="retries on 503 and connection errors")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per request")
    p.add_argument("--token", default=None, help="bearer token (or $GRADSEP_TOKEN)")
    p.set_defaults(func=_client)
