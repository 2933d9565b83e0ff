"""``python -m rave``: the ``rave`` command (``rave.cli``)."""

import sys

from rave.cli import main

sys.exit(main())
