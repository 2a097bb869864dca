"""``python -m urd.cli``: the ``urd`` command."""

import sys

from urd.cli import main

sys.exit(main())
