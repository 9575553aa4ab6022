"""`python -m jaxfog ...`: the same as the `jaxfog` console script."""

import sys

from ._cli import main

sys.exit(main())
