"""``python -m bonecap`` runs the command line."""

import sys

from bonecap.cli import main

sys.exit(main())
