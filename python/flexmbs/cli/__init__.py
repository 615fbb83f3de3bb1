"""The ``flexmbs`` command line (argparse only): main.py builds the parser and runs a command;
one module per command or group of commands (simulate in main.py, evaluate.py, check.py,
optimize.py, reproduce.py for ``demo`` and ``reproduce``)."""
