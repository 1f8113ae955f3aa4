"""``python -m fpp_graph.cli``: the same application as the ``fpp-slam`` command."""

import sys

from fpp_graph.cli.app import main

sys.exit(main())
