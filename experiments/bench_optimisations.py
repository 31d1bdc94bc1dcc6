"""Each optimisation in the code against its plain formulation, forward + backward, one process.

(a) decoder input conv once per crop, (b) sliced CPU 3D convolution vs XLA's, (c) FeatureNet stem
convolving the coordinate channels once, (d) separable gaussian maps, (e) grain prefetch. The
logic lives in `nmjax.bench` (the plain/fast pairs are tested there to agree).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_optimisations.py --preset cpu \
        --out experiments/results/bench_optimisations_cpu.json
"""

from __future__ import annotations

import sys

from nmjax.bench import optimisations_main

if __name__ == "__main__":
    sys.exit(optimisations_main(sys.argv[1:]))
