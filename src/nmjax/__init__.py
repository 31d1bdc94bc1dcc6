"""nmjax: Neural Marionette in JAX/Flax."""

import os

# jaxlib 0.10's CPU backend hands convolutions and reductions to YNNPACK by default. For the
# detector's thin full-resolution convolutions, and above all for their kernel gradients, that
# path is 3-4x slower than XLA's own, and its batch sums (the gradient of a tensor broadcast to
# every frame) 17x slower (docs/performance.md, "CPU convolutions"), so nmjax switches both off
# before JAX creates its CPU client. A user who sets the option in XLA_FLAGS keeps their choice;
# it has no effect on GPU/TPU. Importing nmjax after the first JAX computation is too late for it
# to apply.
YNN_CONVOLUTION_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-individual_convolution,-reduce"
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_cpu_experimental_ynn_fusion_type" not in _flags:
    os.environ["XLA_FLAGS"] = f"{_flags} {YNN_CONVOLUTION_FLAG}".strip()
del _flags
