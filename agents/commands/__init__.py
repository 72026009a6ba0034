"""The command lines (``evflow-*`` console commands; ``python scripts/X.py`` runs the same
``main``): argument parsing, progress and output files over the library."""
