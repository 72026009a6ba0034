"""The command lines (``evflow-*``; ``python scripts/X.py`` runs the same ``main``) over the library."""
