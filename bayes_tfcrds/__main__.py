"""``python -m bayes_tfcrds``: the same as the ``bayes-tfcrds`` command."""

from bayes_tfcrds.cli import main

raise SystemExit(main())
