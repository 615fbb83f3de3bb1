"""``python -m flexmbs``: the command line of flexmbs.cli."""
from flexmbs.cli import main

raise SystemExit(main())
