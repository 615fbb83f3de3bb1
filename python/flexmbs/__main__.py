"""``python -m flexmbs``: the command line of flexmbs.cli.main."""
from flexmbs.cli.main import main

raise SystemExit(main())
