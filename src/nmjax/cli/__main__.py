"""`python -m nmjax.cli COMMAND ...`, the same as `nmjax COMMAND ...`."""

import sys

from nmjax.cli import main

sys.exit(main())
