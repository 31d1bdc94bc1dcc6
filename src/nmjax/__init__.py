"""nmjax: Neural Marionette in JAX/Flax."""

import os

# jaxlib 0.10's CPU backend hands convolutions to YNNPACK by default. For the detector's thin
# full-resolution 3D convolutions, and above all for their kernel gradients, that path is 3-4x
# slower than XLA's own (docs/performance.md, "CPU convolutions"), so nmjax switches it off before
# JAX creates its CPU client. A user who sets the option in XLA_FLAGS keeps their choice; the
# option has no effect on GPU/TPU. Importing nmjax after the first JAX computation is too late
# for it to apply.
YNN_CONVOLUTION_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-individual_convolution"
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_cpu_experimental_ynn_fusion_type" not in _flags:
    os.environ["XLA_FLAGS"] = f"{_flags} {YNN_CONVOLUTION_FLAG}".strip()
del _flags
