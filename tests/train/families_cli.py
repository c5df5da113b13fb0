"""``python -m tests.train.families_cli ARGS``: the ``emlp`` command with the tests' short-range
families registered (:mod:`tests.nn.helpers`), for subprocess and ``torchrun`` tests."""

import sys

import tests.nn.helpers  # noqa: F401 (registers the test-only family "radial")
from emlpack.cli import main

sys.exit(main())
