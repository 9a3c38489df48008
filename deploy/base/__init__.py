"""The floor of ``deploy``: what every audience above shares — the commands' errors
(``errors``), console output and tables (``output``), and a robot's node and belief built from a
scenario or a robot model (``build``). It imports nothing else of ``deploy``."""
