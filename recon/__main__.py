"""`python -m recon ...`: the `recon` command (recon.commands.cli), for an environment
whose scripts folder is not on PATH."""

import sys

from .commands.cli import main

sys.exit(main())
