"""`nmjax bench` as a script: steps/s, frames/s, load vs compute, compile time and peak memory of
the phase-1 and phase-2 train steps (see `nmjax.bench`).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_train.py --preset cpu default \
        --out experiments/results/bench_train_cpu.json
"""

from __future__ import annotations

import sys

from nmjax.cli.bench import bench

if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
