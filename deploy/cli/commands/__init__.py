"""One module per ``semfleet`` command: build its parser, call one library function, print.

Nothing imports a command module but :mod:`deploy.cli.main` (and ``scenario`` its ``frames``
subcommand); what commands share lives in ``deploy/`` beside this package.
"""
