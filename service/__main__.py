"""``python -m service``: the ``bdsfix`` command line."""

from service.commands.cli import entry

entry()
