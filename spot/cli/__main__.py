"""``python -m spot.cli``: the ``spot`` command."""

import sys

from spot.cli import main

if __name__ == "__main__":  # importing the module (tests import every spot module) runs nothing
    sys.exit(main())
