"""`python -m mjstamp.cli`: the `mjstamp` command."""

import sys

from mjstamp.cli import main

sys.exit(main())
