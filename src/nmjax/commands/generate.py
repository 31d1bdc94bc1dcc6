"""`nmjax generate`: see `nmjax.tasks_cli.generate_main`."""

from nmjax.tasks_cli import generate_main as main

__all__ = ["main"]
