"""`nmjax retarget`: see `nmjax.tasks_cli.retarget_main`."""

from nmjax.tasks_cli import retarget_main as main

__all__ = ["main"]
