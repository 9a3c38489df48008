"""``python -m deploy.cli``: the ``semfleet`` command."""

from deploy.cli.main import entry

entry()
