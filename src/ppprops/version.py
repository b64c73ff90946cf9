"""The package version (one place; the CLI, policy files and run records read it)."""

__version__ = "0.1.0"
