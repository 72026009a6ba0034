"""The application built on the library (``agents/``, ``envs/``, ``losses/``): what a user runs.

- ``evflow_cli.commands``: one module per command (``scripts/X.py`` and the ``evflow-*`` console
  commands are thin entry points into them), each with its options as a dataclass
  (``agents/options.py``) and ``run(main)`` turning a user's mistake into one line on stderr.
- ``evflow_cli.campaign``: training that outlives its machine (state kept in ``agents/campaigns/``).
- ``evflow_cli.ablations``: the paper's ablation tables, trained and scored with one budget.
- ``evflow_cli.predict``: flow for a whole recording written to an h5 file, a preview and a summary.
- ``evflow_cli.summary``: model variants and their sizes for tables; ``tensorboard_log``: a
  training run's curves in TensorBoard.

The library never imports this package (``tests/test_imports.py``).
"""
