"""``python -m evojax_motion.cli``: the `evojax-motion` command (`entry.main`)."""

import sys

from evojax_motion.cli.entry import main

sys.exit(main())
