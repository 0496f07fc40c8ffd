"""The oidn-l1 refinement of one evaluated frame under several solves, scored against the evaluation's cached
references (product estimator): does the solve budget change the error? Needs the cache of a finished
`gradsep evaluate --cache runs/evalcache` run (reference passes and frames present).

    PYTHONPATH=. python benchmarks/refine_solve_check.py cbox 64

Run from a folder whose runs/evalcache is that cache (e.g. the main checkout, PYTHONPATH pointing at this one).
A *check* of the refinement's solve on the evaluation frames: nothing is chosen from it (docs/network.md).
"""
import glob
import sys
from pathlib import Path

from gradsep.evaluation.config import EvalConfig, resolve_scenes
from gradsep.evaluation.run import _Runner
from gradsep.model import refine
from gradsep.model.frame import read_frame
from gradsep.model.metrics import relmse_unbiased
from gradsep.model.reconstruct import reconstruct
from gradsep.renderer.scene import load_scene

scene = sys.argv[1] if len(sys.argv) > 1 else "cbox"
spp = int(sys.argv[2]) if len(sys.argv) > 2 else 64
entries, _ = resolve_scenes(())
entry = next(e for e in entries if e.name == scene)
cfg = EvalConfig(scenes=(), spp=(spp,), width=320, height=240, ref_spp=512, output=Path("/tmp/x"),
                 cache_dir=Path("runs/evalcache"), models_dir=Path("models"), ref_spp_cap=10240)
loaded = load_scene(entry.spec, width=320, height=240)
runner = _Runner(cfg, False, print)
src = runner.references(entry, loaded)
ref_spp = {"cbox": 10240, "procedural:90001": 8704, "procedural:90002": 10240, "teapot": 1024}[scene]
pair = src.pair(ref_spp)
assert src.rendered == 0, "rendered passes: cache mismatch"
folder = f"runs/evalcache/evaluate/frames/{scene.replace(':', '-')}"
frame = read_frame(glob.glob(f"{folder}/*spp{spp}-seed0-direct*.exr")[0])
base = reconstruct(frame, "oidn")
solves = {"default (REFINE_CG_TOLERANCE rule)": {}, "mg 2 (before)": {"preconditioner": "mg", "cg_steps": 2},
          "dct 4": {"preconditioner": "dct", "cg_steps": 4}, "mg 4": {"preconditioner": "mg", "cg_steps": 4},
          "mg converged": {"preconditioner": "mg", "cg_steps": 40, "cg_tolerance": 1e-5}}
for label, kwargs in solves.items():
    d_img = refine.refine_layer("direct", base.layers["direct"], frame.layers["direct"], **kwargs)
    d = relmse_unbiased(d_img, pair.first["direct"], pair.second["direct"])
    rest = sum(img for name, img in base.layers.items() if name != "direct")  # 0 for a direct-only frame
    t = relmse_unbiased(d_img + rest, pair.first["total"], pair.second["total"])
    print(scene, spp, label, "direct", f"{d:.6f}", "total", f"{t:.6f}", flush=True)
