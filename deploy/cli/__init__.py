"""The ``semfleet`` command line: ``main`` parses and dispatches, ``commands/`` holds one module per
command (its parser, one call into ``deploy.study``, ``deploy.operator`` or ``deploy.launch``, its
printing), ``args`` and ``scenario_args`` the argument types they share."""
