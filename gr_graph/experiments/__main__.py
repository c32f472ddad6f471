"""``python -m gr_graph.experiments``: see :mod:`gr_graph.experiments.cli`."""

from gr_graph.experiments.cli import main

raise SystemExit(main())
