"""Built-in model declarations: the damper models of models.md and a Duffing example."""
