"""A user-style flow model package living outside ``agents/``: proof that any module honouring
the protocol plugs into our registry, policy wrapper, env rollouts and training loop."""
