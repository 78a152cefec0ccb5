"""``python -m deckland.ros.bag VERB ...`` (same as ``deckland bag VERB ...``)."""

import sys

from deckland.ros.bag.cli import main

sys.exit(main())
