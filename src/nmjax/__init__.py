"""nmjax: Neural Marionette in JAX/Flax."""
