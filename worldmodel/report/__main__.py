"""python -m worldmodel.report publish | headline | recheck | readme (worldmodel/published.py)."""

from worldmodel.published import main

raise SystemExit(main())
