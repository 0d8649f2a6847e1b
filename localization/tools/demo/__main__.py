"""``python -m localization.tools.demo``: the same as ``localization-demo``."""
import sys

from localization.tools.demo.cli import main

sys.exit(main())
