"""`python -m jaxrt.cli`: the `jaxrt` command."""

import sys

from jaxrt.cli import main

sys.exit(main())
