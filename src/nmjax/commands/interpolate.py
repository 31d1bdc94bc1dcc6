"""`nmjax interpolate`: see `nmjax.tasks_cli.interpolate_main`."""

from nmjax.tasks_cli import interpolate_main as main

__all__ = ["main"]
