"""Built-in model declarations: the damper models of docs/models.md and a Duffing example."""
