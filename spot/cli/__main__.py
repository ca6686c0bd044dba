"""``python -m spot.cli``: the ``spot`` command."""

import sys

from spot.cli import main

sys.exit(main())
