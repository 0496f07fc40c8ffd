"""`gradsep render | reference | dataset`: argparse only; handlers import Mitsuba lazily."""

from __future__ import annotations

import argparse


def _render(args: argparse.Namespace) -> int:
    from renderer.render import render_command

    return render_command(args)


def _reference(args: argparse.Namespace) -> int:
    from renderer.reference import reference_command

    return reference_command(args)


def _dataset(args: argparse.Namespace) -> int:
    from renderer.dataset import dataset_command

    return dataset_command(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render a G-PT frame (base + gradients + features per illumination layer)")
    p.add_argument("scene", help="Mitsuba 3 XML scene path or procedural:SEED")
    p.add_argument("--spp", type=int, required=True, help="samples per pixel")
    p.add_argument("--width", type=int, default=None, help="override the scene's film width")
    p.add_argument("--height", type=int, default=None, help="override the scene's film height")
    p.add_argument("--max-depth", type=int, default=None,
                   help="Mitsuba's convention: 2 = direct light only, -1 = unbounded (default: the scene's)")
    p.add_argument("--seed", type=int, default=0, help="sampler seed")
    p.add_argument("--layers", default="direct,indirect",
                   help="comma-separated illumination layers to render: direct, indirect (default both); "
                        "color alone renders the unseparated image")
    p.add_argument("--shift", choices=("hybrid", "replay"), default=None,
                   help="shift mapping: hybrid (reconnection + replay, the default) or replay")
    p.add_argument("--no-gradients", action="store_true",
                   help="primal-only: the same layers and features, no offset paths and no gradients "
                        "(about the cost of a plain path tracer)")
    p.add_argument("-D", "--define", action="append", default=[], metavar="NAME=VALUE",
                   help="override a <default> parameter of the XML scene (repeatable)")
    p.add_argument("-o", "--output", required=True, help="output frame (.exr)")
    p.set_defaults(func=_render)

    p = sub.add_parser("reference", help="render a reference with Mitsuba's path integrator (R G B + layers)")
    p.add_argument("scene", help="Mitsuba 3 XML scene path or procedural:SEED")
    p.add_argument("--spp", type=int, required=True, help="samples per pixel")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--max-depth", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tile-spp", type=int, default=None,
                   help="samples per pass; passes are averaged so large spp fits in memory")
    p.add_argument("-D", "--define", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("-o", "--output", required=True, help="output reference (.exr)")
    p.set_defaults(func=_reference)

    p = sub.add_parser("dataset", help="render N procedural frames plus a manifest (shardable, resumable)")
    p.add_argument("--count", type=int, required=True, help="number of frames in the whole dataset")
    p.add_argument("--spp", type=int, required=True)
    p.add_argument("--size", default="256x256", help="WxH")
    p.add_argument("--first-seed", type=int, default=1000, help="seed of frame 0; frame i uses first-seed + i")
    p.add_argument("--max-depth", type=int, default=None)
    p.add_argument("--shard", default="0/1", help="i/n: render frames i, i+n, i+2n, ...")
    p.add_argument("--pairs", action="store_true",
                   help="also render an independent second realization of every frame (another sampler seed): "
                        "the Noise2Noise targets `gradsep train` uses when present")
    p.add_argument("-o", "--output", required=True, help="dataset folder")
    p.set_defaults(func=_dataset)
