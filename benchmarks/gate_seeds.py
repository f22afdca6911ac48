"""How far apart good builds of one organ land, against how much worse broken ones are: the
relative validation error of 8 seeds of the bar's 5-path build (the recipe of
tests/surrogate/test_train_cli.py's noise test), of untrained builds and of builds without the
physics layout, with the rebuild gate's ratios and bounds between them (REPLACE_EXCUSE_CEILING).

    python benchmarks/gate_seeds.py > reports/gate/seeds.txt
"""

import contextlib
import io
import itertools
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service.build import relative_error, worse_at_least, worse_by
from service.cli import main
from service.mesh import TetMesh
from service.phantoms import grid_tets
from tests.conftest import write_bar_scene

nodes, tets = grid_tets((8, 2, 2), 0.5)
bar, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
from service.bench import machine

print("machine:", json.dumps(machine.describe()))
tmp = Path(tempfile.mkdtemp())
scene = write_bar_scene(tmp / "scene", bar, samples=150)
common = ["train", str(scene), "--data", str(tmp / "data"), "--workers", "0", "--hidden", "32", "--rank", "8"]
vals = {}
runs = [(f"good{s}", ["--epochs", "20", "--seed", str(s)]) for s in range(1, 9)]
runs += [(f"untrained{s}", ["--epochs", "1", "--no-physics-skip", "--seed", str(s)]) for s in range(1, 4)]
runs += [(f"nophys{s}", ["--epochs", "20", "--no-physics-skip", "--seed", str(s)]) for s in range(1, 4)]
for name, extra in runs:
    store = tmp / f"store-{name}"
    with contextlib.redirect_stderr(io.StringIO()):
        assert main([*common, "--store", str(store), *extra]) == 0
    vals[name] = json.loads((store / "bar" / "manifest.json").read_text())["training"]["validation"]
    v = vals[name]
    print(name, f"rel {relative_error(v):.4f} share {v['relative_error_path_se'] / relative_error(v):.3f}", flush=True)
good = [k for k in vals if k.startswith("good")]
ratios = [(worse_by(vals[a], vals[b]), worse_at_least(vals[a], vals[b])) for a, b in itertools.permutations(good, 2)]
r = np.array([t for t, _ in ratios])
lb = np.array([l for _, l in ratios])
print(f"good pairs: ratio max {r.max():.2f}, >2x {np.sum(r > 2)} of {r.size}; bound max {lb.max():.2f}")
for bad in [k for k in vals if not k.startswith("good")]:
    t = [worse_by(vals[bad], vals[g]) for g in good]
    l = [worse_at_least(vals[bad], vals[g]) for g in good]
    print(f"{bad} over good: ratio {min(t):.1f}-{max(t):.1f}x, bound {min(l):.2f}-{max(l):.2f}x")
