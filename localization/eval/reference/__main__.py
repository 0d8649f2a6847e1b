"""``python -m localization.eval.reference [BAG ...]`` (``cli.main``)."""
from localization.eval.reference.cli import main

raise SystemExit(main())
