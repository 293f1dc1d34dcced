"""``python -m rigidjax._cli``: the ``rigidjax`` command."""

import sys

from .parser import main

sys.exit(main())
