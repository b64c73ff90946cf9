"""Task descriptions (``*.toml``): the prose of the built-in tasks."""
