"""Command-line subcommands: one module each, registered in core.cli."""
