"""One timed build of a scene with training settings of its own, scored as `elastreg bench minutes`
scores its rows (minutes.timed_build: its plan, an empty data folder, its test set) with
--features and --weight-decay given, so that two settings can be built the same way and compared.

`bench minutes` builds at the defaults; session 31's 60-minute liver row trained on one thread
(the bench's, before 169f5ea), so --threads sets the training's threads to compare with it.

    python benchmarks/settings_build.py benchmarks/scenes/liver_paper.toml --minutes 60 \\
        --features 256 --weight-decay 0 --threads 1 --store STORE \\
        --out reports/settings-s32/old_settings_build_row.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench import machine
from service.bench.minutes import test_set, timed_build
from service.config import flush_subnormals, limit_threads
from service.scene import load_scene
from service.surrogate.train import TrainConfig


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--minutes", type=float, required=True)
    p.add_argument("--features", type=int, required=True)
    p.add_argument("--weight-decay", type=float, required=True)
    p.add_argument("--threads", type=int, default=machine.cores(), help="training threads (default: a core each)")
    p.add_argument("--store", type=Path, required=True, help="where the entry is kept")
    p.add_argument("--test-data", type=Path, default=Path.home() / ".cache" / "elastreg" / "test-data")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    flush_subnormals()  # before torch's threads, as elastreg train
    limit_threads(1)  # the bench's setting, which the build's training leaves for --threads
    scene = load_scene(args.scene)
    config = TrainConfig(physics_skip=True, features=args.features, weight_decay=args.weight_decay)
    row = timed_build(scene, args.minutes, test_set(scene, 40, args.test_data, 2), workers=2, keep=args.store,
                      config=config, threads=args.threads)  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(row, indent=1))
    print(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":  # Dask's workers import this module: the build runs only here
    raise SystemExit(main())
