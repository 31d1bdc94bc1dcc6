"""nmjax: Neural Marionette in JAX/Flax."""

import os

# jaxlib 0.10's CPU backend hands convolutions and reductions to YNNPACK by default. A trace of
# the phase-1 step found that path the largest cost of the detector's thin full-resolution
# convolutions (above all their kernel gradients) and of its batch sums (the gradient of a
# tensor broadcast to every frame): docs/performance.md, "CPU convolutions", describes it; no
# results file holds that trace. So nmjax switches both off before JAX creates its CPU client.
# A user who sets the option in XLA_FLAGS keeps their choice; it has no effect on GPU/TPU.
# Importing nmjax after the first JAX computation is too late for it to apply.
YNN_CONVOLUTION_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-individual_convolution,-reduce"
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_cpu_experimental_ynn_fusion_type" not in _flags:
    os.environ["XLA_FLAGS"] = f"{_flags} {YNN_CONVOLUTION_FLAG}".strip()
del _flags
