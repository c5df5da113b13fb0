"""``python -m emlpack.cli``: the ``emlp`` command."""

import sys

from emlpack.cli import main

sys.exit(main())
