"""``python -m nlpsf``: the same as the ``nlpsf`` console script."""

from .cli import main

raise SystemExit(main())
