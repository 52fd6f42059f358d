"""``python -m service``: the ``bdsfix`` command line."""

import sys

from service.commands.cli import main

sys.exit(main())
