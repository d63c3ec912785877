"""``python -m slam.cli``: the ``slam`` command."""

import sys

from slam.cli import main

sys.exit(main())
