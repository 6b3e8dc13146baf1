"""``python -m dcc_fg`` runs the ``dcc-fg`` command line."""

import sys

from dcc_fg.cli import main

sys.exit(main())
