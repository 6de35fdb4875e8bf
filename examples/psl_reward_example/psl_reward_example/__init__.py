"""An example package of reward components for psl (registered in pyproject.toml)."""
