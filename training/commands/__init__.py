"""Command-line subcommands that drive training (``dataset``, ``train``, ``evaluate``): one module each, the
same form as :mod:`unipixie.core.commands`; the root command line (``unipixie/cli.py``) lists this package."""
